"""quatrack.service — the HTTP/WebSocket service behind ``quatrack serve``.

``app.create_app(settings)`` builds the FastAPI app; ``routes`` holds the endpoints, ``sessions``
the WebSocket tracking sessions, ``schemas`` the pydantic models at the edge, ``errors`` the
contract's error body, ``settings`` the limits (``QUATRACK_*`` environment variables),
``server.BackgroundServer`` runs it in a thread (tests, demo, bench).
"""
