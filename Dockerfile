# quatrack: a plain mirror of the README's steps (no Docker engine runs on the build machines).
FROM python:3.11-slim
ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1
RUN useradd --create-home --uid 10001 quatrack
WORKDIR /app
COPY . /app
RUN pip install --no-cache-dir /app
USER quatrack
# Until the service lands (issue 6), the container runs the tracker's reproduction experiment.
ENTRYPOINT ["quatrack"]
CMD ["bench", "ude-cube"]
