"""simgap_viz: the viser web GUI and headless Rerun recordings over the simgap engine."""
