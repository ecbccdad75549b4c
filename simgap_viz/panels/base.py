"""Shared helpers of the panels: a small base class and guarded callbacks."""

from __future__ import annotations


class Panel:
    """A tab's handles. ``buttons`` maps stage name -> button handle (enabled by the app)."""

    def __init__(self, app):
        self.app = app
        self.buttons = {}

    def on(self, handle, fn) -> None:
        """Call ``fn(value)`` when ``handle`` changes, unless the app is syncing its handles.

        ``fn`` runs through ``app.guarded``: a bad value gives a notification, never an exception
        in viser's callback thread.
        """
        app = self.app

        def cb(_event):
            if getattr(app, "_syncing", False):
                return
            app.guarded(fn, handle.value)

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
