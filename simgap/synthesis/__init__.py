"""Symbolic controller synthesis: grid, abstraction, games, controller, rollouts."""
