# quatrack: a plain mirror of the README's steps (no Docker engine runs on the build machines).
# Build: docker build -t quatrack .   Run: docker run -p 8000:8000 [-e QUATRACK_API_TOKEN=...] quatrack
# One worker process per CPU the container may use (its --cpus quota; QUATRACK_WORKERS overrides).
# docker stop sends SIGTERM: open tracking sessions are closed with code 1012. Replicas: deploy/.
FROM python:3.11-slim
ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 \
    QUATRACK_STORE=/data/models QUATRACK_HOST=0.0.0.0 QUATRACK_PORT=8000
RUN useradd --create-home --uid 10001 quatrack && mkdir -p /data/models && chown quatrack /data/models
# The source is copied to /src and installed (not editable); the commands run in /app, which holds
# only the examples (deploy/'s `train examples/cookie-box/object.json`): run in the source folder,
# its quatrack/ shadowed the installed package (`python -m quatrack` failed).
COPY . /src
RUN pip install --no-cache-dir /src && mkdir -p /app/examples && cp -r /src/examples/cookie-box /app/examples/
WORKDIR /app
USER quatrack
# The bundled example object, trained at build time into $QUATRACK_STORE (≈ 5 s).
RUN quatrack train examples/cookie-box/object.json
EXPOSE 8000
HEALTHCHECK --interval=30s --timeout=5s --start-period=20s --retries=3 \
    CMD ["python", "-c", "import os, sys, urllib.request; sys.exit(urllib.request.urlopen('http://127.0.0.1:%s/healthz' % os.environ.get('QUATRACK_PORT', '8000'), timeout=4).status != 200)"]
ENTRYPOINT ["quatrack"]
CMD ["serve"]
