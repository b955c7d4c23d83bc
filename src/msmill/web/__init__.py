"""Local web app and HTTP JSON API (``msmill serve``): an edge over :mod:`msmill.model`.

Import :func:`msmill.web.app.create_app` to embed the app (FastAPI), or run
``msmill serve``. Documentation: ``docs/web.md``.
"""
