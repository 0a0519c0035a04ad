"""What the page's panels share about viser's widgets and viser's thread."""

from __future__ import annotations

import asyncio
import concurrent.futures
from collections.abc import Callable
from typing import Any

import viser

PAGE_CALL_TIMEOUT_S = 5.0


_MARKDOWN_SPECIAL = str.maketrans({c: "\\" + c for c in "\\`*_[]()#+-!|{}~"})


def as_text(text: str) -> str:
    """``text`` (a file name, a message with one in it) for viser's markdown: shown as it is, never
    read as HTML or markdown (a name with ``<img>`` in it once made an image on the page)."""
    return (str(text).replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
            .translate(_MARKDOWN_SPECIAL))


def assign(handle: Any, value: Any) -> None:
    """Set a widget's value from the server (viser types ``value`` read-only on some handles)."""
    handle.value = value


def on_page_thread(server: viser.ViserServer, fn: Callable[[], None], timeout_s: float = PAGE_CALL_TIMEOUT_S) -> bool:
    """Run ``fn`` (which updates the page) on viser's own event-loop thread and wait for it;
    whether it ran. ``fn``'s exceptions reach the caller.

    viser lets any thread update the page, but each update wakes the page's sender with
    ``asyncio.Event.set()`` called on the updating thread (viser 1.1's message buffer), and
    asyncio's events are not thread-safe: when the sender parks on the event at that moment
    the update fails with "deque mutated during iteration" (seen here once in three minutes on
    a loaded machine, the rest of that tick's drawing lost), or worse, the sender misses the
    wake-up and that browser's stream stops. On viser's thread the same calls are safe, so the
    threads that draw many times a second (the live and replay dashboards, the fleet page)
    hand their drawing to it. Called on that thread, ``fn`` simply runs. A server that has
    stopped, or a thread busy past ``timeout_s``, means ``fn`` is not run (False): the caller
    draws the next state instead.
    """
    loop = server.get_event_loop()
    try:
        on_loop = asyncio.get_running_loop() is loop
    except RuntimeError:  # no loop runs on this thread
        on_loop = False
    if on_loop:
        fn()
        return True
    done: concurrent.futures.Future[None] = concurrent.futures.Future()

    def call() -> None:
        if not done.set_running_or_notify_cancel():  # the caller gave up waiting: the state is old
            return
        try:
            fn()
        except BaseException as exc:  # noqa: BLE001 - handed to the caller, who decides
            done.set_exception(exc)
        else:
            done.set_result(None)

    try:
        loop.call_soon_threadsafe(call)
    except RuntimeError:  # the loop is closed: the server has stopped
        return False
    try:
        done.result(timeout_s)
    except concurrent.futures.TimeoutError:
        done.cancel()  # not started yet: it never will be
        return False
    return True
