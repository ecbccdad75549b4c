"""Turning command-line options (experiment, profile, dataset, system) into the app's inputs."""

from __future__ import annotations

from typing import Optional

from simgap.errors import SimgapError

from . import engine
from .settings import Settings


def app_inputs(experiment: Optional[str] = None, profile: Optional[str] = None, dataset: Optional[str] = None,
               system: Optional[str] = None):
    """(settings, dataset or None, spec or None, arena map or None) for the app."""
    settings = Settings()
    spec = arena = data = None
    if experiment:
        settings, spec, arena = settings_from_experiment(experiment, profile)
    if system:
        settings = settings.replace(system=system, simulator=engine.default_simulator(system, settings.simulator))
    settings = settings.replace(eta=engine.default_eta(engine.make_system(settings))) \
        if len(settings.eta) != engine.make_system(settings).n else settings
    if dataset:
        from simgap.dataset import load_dataset
        data = load_dataset(dataset)
    return settings, data, spec, arena


def settings_from_experiment(name: str, profile: Optional[str]):
    try:
        from simgap.config import load_experiment
    except ImportError:
        raise SimgapError("--experiment needs simgap.config, which this engine version does not have") from None
    exp = load_experiment(name, profile)
    return from_experiment(exp)


def from_experiment(exp):
    """Map an engine experiment object to (Settings, spec, arena)."""
    raise SimgapError("experiment loading is not wired yet")
