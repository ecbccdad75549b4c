"""Scene layers: pure functions from engine results to geometry arrays (display coordinates).

Both the viser app and the Rerun recorder draw from these, so a layer is tested once.
"""
