"""Views learned by tracking sessions (issue 12, item 3), off unless ``QUATRACK_LEARN_VIEWS`` names the object.

A session of such an object runs its tracker with ``learn=True``
(:func:`~quatrack.service.tracker_factory.make_tracker`); when the session ends, the views it
learned are merged into the stored model (:func:`quatrack.viewsets.learn.merge_learned`: the
stored model is re-read under the store's lock, so two sessions of one object ending together
keep each other's views, and written by an atomic rename, so no reader sees half a model). The
registry's watcher then sees the new stamp and serves the learned model to new sessions;
running sessions keep the model they started with.
"""

from __future__ import annotations

import asyncio
import logging

from quatrack.viewsets.errors import StoreError
from quatrack.viewsets.learn import check_can_store, merge_learned

from .settings import Settings

log = logging.getLogger("quatrack.service")


_UNSTORABLE: set[tuple[str, str]] = set()  # (store, object) already logged as unable to take views


def learns(settings: Settings, name: str) -> bool:
    """Whether sessions of object ``name`` learn views (``QUATRACK_LEARN_VIEWS``: names or ``*``),
    and their store can take them: with a store (or model folder) the server cannot write in,
    sessions learned for nothing — the views were refused at each session's end, and the
    ``ready`` message said ``"learns": true`` — so they do not learn, and the log says why once."""
    if not ("*" in settings.learn_views or name in settings.learn_views):
        return False
    try:
        check_can_store(settings.store, name)
    except StoreError as exc:
        key = (str(settings.store), name)
        if key not in _UNSTORABLE:
            _UNSTORABLE.add(key)
            log.warning("object %s: QUATRACK_LEARN_VIEWS names it, but its sessions learn nothing: %s", name, exc)
        return False
    return True


def store_views(settings: Settings, name: str, tracker, session_id: str | None = None) -> int:
    """Merge the views ``tracker`` learned into ``settings.store``'s model ``name``; returns how many
    were added. Blocking (file I/O): run it on a worker thread. Never raises: a store that cannot
    take them (object deleted or retrained on another mesh, disk full) is logged (with the
    session's id as the ``session_id`` field when given, as its other lines carry it)."""
    extra = {"session_id": session_id} if session_id is not None else None
    learned = tracker.learned_viewsets() if tracker is not None else []
    if not learned:
        return 0
    try:
        folder, added, total = merge_learned(settings.store, name, learned, tracker.model.mesh,
                                             tracker.params.learn_max_views, tracker.params.learn_min_angle_deg,
                                             learned_on=tracker.model)
    except Exception as exc:  # the session is over: nothing to answer, only to log
        log.error("object %s: the %d view(s) a session learned were not stored: %s", name, len(learned), exc, extra=extra)
        return 0
    if added:
        log.info("object %s: %d learned view(s) stored in %s (%d learned in all)", name, added, folder, total,
                 extra=extra)
    return added


async def store_session_views(session) -> int:
    """At a session's end: store its tracker's learned views (:func:`store_views`) on the
    session's executor, if its object learns."""
    if not learns(session.settings, session.name) or session.tracker is None:
        return 0
    loop = asyncio.get_running_loop()
    try:
        return await loop.run_in_executor(session.executor, store_views, session.settings, session.name, session.tracker,
                                          session.sid)
    except RuntimeError:  # the executor is shut down (server stopping): store from this thread
        return store_views(session.settings, session.name, session.tracker, session.sid)
