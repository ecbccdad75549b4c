"""Shared helpers of the panels: a small base class and guarded callbacks."""

from __future__ import annotations

import threading


class Panel:
    """A tab's handles. ``buttons`` maps stage name -> button handle (enabled by the app)."""

    def __init__(self, app):
        self.app = app
        self.buttons = {}

    def on(self, handle, fn, debounce: float | None = None, ready=None) -> None:
        """Call ``fn(value)`` when ``handle`` changes, unless the app is syncing its handles.

        ``fn`` runs through ``app.guarded``: a bad value gives a notification, never an exception
        in viser's callback thread. With ``debounce`` > 0, changes coming from a browser (typing
        in a text field) are applied only once the value has been stable for that many seconds,
        so half-typed terms do not raise notifications; changes made from Python apply at once.
        ``ready(value)`` True marks a browser value complete enough to apply without the wait (a
        valid number: typing on re-applies, and the app supersedes the job the earlier value started).
        """
        app = self.app
        timer = {"t": None}
        if debounce is None:  # typed values (numbers, text) pass through invalid prefixes like "0."
            debounce = 0.5 if type(handle).__name__ in ("GuiNumberHandle", "GuiTextHandle") else 0.0

        def apply():
            app.guarded(fn, handle.value)

        def cb(event):
            if getattr(app, "_syncing", False):
                return
            if debounce > 0 and getattr(event, "client", None) is not None:
                if timer["t"] is not None:
                    timer["t"].cancel()
                if ready is not None and ready(handle.value):
                    apply()
                    return
                timer["t"] = threading.Timer(debounce, apply)
                timer["t"].daemon = True
                timer["t"].start()
                return
            apply()

        handle.on_update(cb)

    def sync_from_settings(self) -> None:
        """Show the app's current settings in this panel's handles."""

    def set_quiet(self, handle, value) -> None:
        """Set a handle's value without firing the app logic."""
        app = self.app
        prev = getattr(app, "_syncing", False)
        app._syncing = True
        try:
            handle.value = value
        finally:
            app._syncing = prev


def fmt_vec(v) -> str:
    return "" if v is None else ", ".join(f"{x:g}" for x in v)
