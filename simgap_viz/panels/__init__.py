"""GUI panels of the app, one module per tab; each exposes ``build(app)`` returning its handles."""
