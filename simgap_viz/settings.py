"""The app's knobs as one plain, validated, hashable value.

:class:`Settings` holds every control of the GUI (and of ``simgap record``). Each pipeline
stage depends on a subset of them; :meth:`Settings.stage_key` hashes exactly that subset
(plus the keys of the stages before it), so results are cached per configuration and a
change of, say, delta re-runs certification but reuses the cached data.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass, field
from typing import Optional, Tuple

from simgap.errors import SimgapError

STAGES = ("collect", "certify", "synthesize", "rollout", "refine")

# which settings each stage reads (on top of everything its predecessor reads)
_STAGE_FIELDS = {
    "collect": ("system", "steps", "simulator", "noise_std", "epsilon", "n_runs", "seed", "experiment",
                "profile", "data_source"),
    "certify": ("delta1", "delta2", "confidence", "degree", "terms", "concentration", "value_range"),
    "synthesize": ("eta", "hold", "use_gap"),
    "rollout": ("n_rollouts", "x0", "horizon", "rollout_seed"),
    "refine": (),
}
_PREDECESSOR = {"collect": None, "certify": "collect", "synthesize": "certify", "rollout": "synthesize",
                "refine": "certify"}

CONCENTRATIONS = ("chebyshev", "bernstein", "subgaussian")


@dataclass
class Settings:
    """Every knob of the method, with the paper's symbols.

    Attributes
    ----------
    system : str
        Built-in system name (``pendulum``, ``turtlebot``) or ``refined`` for a refined model.
    steps : int
        Base periods per sampling period k (tau = k * base_tau).
    simulator : str
        Simulator backend kind (``numpy``, ``pybullet_pendulum``, ``pybullet_turtlebot``).
    noise_std : float
        Actuation noise standard deviation of the simulator (input units).
    epsilon : float
        Cover radius epsilon (state units, Euclidean), > 0.
    n_runs : int
        N1hat, simulator runs per (x_r, u), >= 2.
    delta1, delta2 : tuple of float or None
        Per-dimension margins delta_1i, delta_2i (state units), > 0; ``None`` means "derive them
        from ``confidence``".
    confidence : float or None
        Target joint confidence 1 - sum_i (beta_1i + beta_2i), in (0, 1).
    degree : int
        Total degree of the monomial basis p_i(x, u).
    terms : str
        Extra basis terms, comma separated (e.g. ``sin(x1), x2*u1``), parsed by the engine.
    concentration : str
        Tail bound for beta: ``chebyshev`` (the paper's), ``bernstein``, ``subgaussian``.
    value_range : float or None
        Known range b of the simulator's next state per run (state units), needed by ``bernstein``.
    eta : tuple of float
        Grid cell widths of the abstraction (state units).
    hold : int
        Sampling periods an input is held in synthesis.
    use_gap : bool
        Synthesize against f + [-gamma, gamma] (True) or the nominal f alone (False).
    n_rollouts, horizon : int
        Closed-loop rollouts R and their length T (sampling periods).
    x0 : tuple of float or None
        Initial state of the rollouts (None: the experiment's initial state).
    data_source : str
        ``""`` for data collected with these settings, else the hash of a loaded dataset.
    """

    system: str = "pendulum"
    steps: int = 1
    simulator: str = "numpy"
    noise_std: float = 0.05
    epsilon: float = 0.05
    n_runs: int = 100
    seed: int = 0
    experiment: str = ""
    profile: str = ""
    data_source: str = ""
    delta1: Optional[Tuple[float, ...]] = None
    delta2: Optional[Tuple[float, ...]] = None
    confidence: Optional[float] = 0.9
    degree: int = 2
    terms: str = ""
    concentration: str = "chebyshev"
    value_range: Optional[float] = None
    eta: Tuple[float, ...] = (0.01, 0.02)
    hold: int = 1
    use_gap: bool = True
    n_rollouts: int = 1000
    horizon: int = 100
    x0: Optional[Tuple[float, ...]] = None
    rollout_seed: int = 0
    extra: dict = field(default_factory=dict)

    def replace(self, **changes) -> "Settings":
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        for k, v in d.items():
            if isinstance(v, tuple):
                d[k] = list(v)
        return d

    # ----- validation ------------------------------------------------------------------
    def validate(self, n: Optional[int] = None) -> "Settings":
        """Raise :class:`SimgapError` naming the first bad value; return self otherwise.

        ``n`` is the state dimension, to check per-dimension vectors.
        """
        def pos(name, v):
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise SimgapError(f"{name} must be a finite number > 0, got {v!r}")

        pos("epsilon", self.epsilon)
        if int(self.n_runs) != self.n_runs or self.n_runs < 2:
            raise SimgapError(f"N1hat (runs per pair) must be an integer >= 2, got {self.n_runs!r}")
        if int(self.steps) != self.steps or self.steps < 1:
            raise SimgapError(f"steps must be an integer >= 1, got {self.steps!r}")
        if not (math.isfinite(self.noise_std) and self.noise_std >= 0):
            raise SimgapError(f"noise std must be >= 0, got {self.noise_std!r}")
        for name in ("delta1", "delta2"):
            v = getattr(self, name)
            if v is not None:
                if n is not None and len(v) != n:
                    raise SimgapError(f"{name} needs {n} values (one per state dimension), got {len(v)}")
                for x in v:
                    pos(name, x)
        if (self.delta1 is None or self.delta2 is None) and self.confidence is None:
            raise SimgapError("give delta_1 and delta_2 per dimension, or a target confidence")
        if self.confidence is not None and not (0.0 < self.confidence < 1.0):
            raise SimgapError(f"target confidence must be in (0, 1), got {self.confidence!r}")
        if int(self.degree) != self.degree or not (0 <= self.degree <= 6):
            raise SimgapError(f"basis degree must be an integer in 0..6, got {self.degree!r}")
        if self.value_range is not None and not (math.isfinite(self.value_range) and self.value_range > 0):
            raise SimgapError(f"range b must be > 0 (or empty for unknown), got {self.value_range!r}")
        if self.concentration not in CONCENTRATIONS:
            raise SimgapError(f"concentration must be one of {', '.join(CONCENTRATIONS)}, got {self.concentration!r}")
        if n is not None and len(self.eta) != n:
            raise SimgapError(f"grid eta needs {n} values (one per state dimension), got {len(self.eta)}")
        for x in self.eta:
            pos("grid eta", x)
        if int(self.hold) != self.hold or self.hold < 1:
            raise SimgapError(f"hold steps must be an integer >= 1, got {self.hold!r}")
        if int(self.n_rollouts) != self.n_rollouts or not (1 <= self.n_rollouts <= 100000):
            raise SimgapError(f"rollout count must be an integer in 1..100000, got {self.n_rollouts!r}")
        if int(self.horizon) != self.horizon or not (1 <= self.horizon <= 100000):
            raise SimgapError(f"rollout horizon must be an integer in 1..100000, got {self.horizon!r}")
        if self.x0 is not None and n is not None and len(self.x0) != n:
            raise SimgapError(f"initial state needs {n} values, got {len(self.x0)}")
        return self

    # ----- cache keys ------------------------------------------------------------------
    def stage_fields(self, stage: str) -> dict:
        """The settings ``stage`` depends on, including its predecessors'."""
        if stage not in _STAGE_FIELDS:
            raise SimgapError(f"unknown stage {stage!r}; stages: {', '.join(STAGES)}")
        out = {}
        s = stage
        while s is not None:
            for k in _STAGE_FIELDS[s]:
                v = getattr(self, k)
                out[k] = list(v) if isinstance(v, tuple) else v
            s = _PREDECESSOR[s]
        return out

    def stage_key(self, stage: str) -> str:
        """Configuration hash (16 hex digits) of everything ``stage``'s result depends on."""
        blob = json.dumps({"stage": stage, **self.stage_fields(stage)}, sort_keys=True, default=str)
        return hashlib.sha256(blob.encode()).hexdigest()[:16]


def parse_vector(text: str, name: str, n: Optional[int] = None, allow_empty: bool = False):
    """Parse ``"0.05, 0.1"`` into a tuple of floats (one value is broadcast to n).

    Raises :class:`SimgapError` naming ``name`` for anything unparseable.
    """
    text = (text or "").strip()
    if not text:
        if allow_empty:
            return None
        raise SimgapError(f"{name}: empty; give one number or {n or 'several'} comma-separated numbers")
    try:
        vals = tuple(float(t) for t in text.replace(";", ",").split(",") if t.strip())
    except ValueError:
        raise SimgapError(f"{name}: cannot parse {text!r} as comma-separated numbers") from None
    if not all(math.isfinite(v) for v in vals):
        raise SimgapError(f"{name}: values must be finite, got {text!r}")
    if n is not None:
        if len(vals) == 1:
            vals = vals * n
        elif len(vals) != n:
            raise SimgapError(f"{name}: need 1 or {n} values, got {len(vals)}")
    return vals
