"""A headless run of the stages for ``simgap record``: the same engine calls as the app's buttons.

:func:`compute` fills in every stage up to ``upto`` that was not given as a file, using the
engine through :mod:`simgap_viz.engine` (collection, certification, synthesis, rollouts).
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field

from simgap.errors import SimgapError

from . import engine
from .jobs import JobContext

ORDER = ("collect", "certify", "synthesize", "rollout")


@dataclass
class Results:
    system: object
    spec: object = None
    dataset: object = None
    certificate: object = None
    synthesis: object = None
    rollouts: object = None
    seconds: dict = field(default_factory=dict)


def load_synthesis(path, system):
    """A saved controller (``Controller.save``) as a synthesis result (controller + its stats)."""
    from simgap.synthesis.controller import Controller, SynthesisResult
    ctrl = Controller.load(path, system=system)
    return SynthesisResult(ctrl, dict(ctrl.meta.get("stats", {})))


def compute(settings, *, experiment=None, spec=None, arena=None, upto: str = "rollout", dataset=None,
            certificate=None, synthesis=None, rollouts=None, executor: str = "local", verbose: bool = True) -> Results:
    """Run the stages up to ``upto`` (collect, certify, synthesize, rollout) that were not given."""
    if upto not in ORDER:
        raise SimgapError(f"--upto must be one of {', '.join(ORDER)}, got {upto!r}")
    system = dataset.system if dataset is not None else engine.make_system(settings, experiment)
    settings.validate(system.n)
    spec = spec or engine.default_spec(system, arena if system.name == "turtlebot" else None)
    out = Results(system=system, spec=spec, dataset=dataset, certificate=certificate, synthesis=synthesis,
                  rollouts=rollouts)
    need = ORDER[:ORDER.index(upto) + 1]

    def log(msg):
        if verbose:
            print(msg, file=sys.stderr, flush=True)

    def timed(stage, fn):
        t0 = time.perf_counter()
        r = fn(JobContext(name=stage))
        out.seconds[stage] = time.perf_counter() - t0
        log(f"{stage}: {out.seconds[stage]:.2f} s")
        return r

    if out.dataset is None and (upto == "collect" or ("certify" in need and out.certificate is None)):
        engine.require("collect")
        out.dataset = timed("collect", lambda ctx: engine.collect(settings, system, ctx, experiment=experiment,
                                                                   executor=executor))
    if "certify" in need and out.certificate is None:  # recorded even when synthesis ignores it
        engine.require("certify")
        out.certificate = timed("certify", lambda ctx: engine.certify(out.dataset, settings, ctx))
    if "synthesize" in need and out.synthesis is None:
        engine.require("synthesize")
        cert = out.certificate if settings.use_gap else None
        out.synthesis = timed("synthesize", lambda ctx: engine.synthesize(system, spec, cert, settings, ctx))
        if out.synthesis.empty:
            log("synthesize: empty winning domain: " + str(out.synthesis.stats.get("diagnosis", "")))
    if "rollout" in need and out.rollouts is None and out.synthesis is not None and not out.synthesis.empty:
        engine.require("rollout")
        out.rollouts = timed("rollout", lambda ctx: engine.rollout(system, spec, out.synthesis, settings, ctx,
                                                                   experiment=experiment,
                                                                   arena=arena if system.name == "turtlebot" else None))
    return out
