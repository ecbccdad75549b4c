"""simgap_viz: the interactive viser app and headless Rerun recordings over the simgap engine.

The engine (``simgap``) does every computation; this package only shows it:

* :mod:`simgap_viz.app` -- :class:`SimgapApp`, the viser web GUI (``simgap gui``);
* :mod:`simgap_viz.record` -- :func:`record_run`, a headless ``.rrd`` recording (``simgap record``);
* :mod:`simgap_viz.layers` -- pure geometry builders shared by both (numpy in, arrays out).
"""
