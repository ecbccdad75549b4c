"""The experiment-file schema: every section and key an experiment TOML may hold, with types and ranges.

Checked with pydantic (strict: no silent type coercion; unknown sections and keys are errors).
:func:`validate` turns pydantic's errors into one :class:`~simgap.errors.SimgapError` that names
the file, the section as written in the file (``[profiles.small.collect]`` when a profile set
it), the key, what is wrong and, for an unknown name, the nearest valid one.

A new stage option is added here, as a field of its section, and nowhere else.
"""

from __future__ import annotations

import difflib
from pathlib import PurePosixPath
from typing import Annotated, Any, Literal, Optional, Union, get_args

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError, model_validator

from .errors import SimgapError
from .systems import MAX_STEPS
from .typed import spelling

Int1 = Annotated[int, Field(ge=1)]
#: base periods per sampling period (at most MAX_STEPS: every transition evaluates the model so often)
Steps = Annotated[int, Field(ge=1, le=MAX_STEPS)]
Int0 = Annotated[int, Field(ge=0)]
Finite = Annotated[float, Field(allow_inf_nan=False)]
Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]
Probability = Annotated[float, Field(gt=0, lt=1)]


def _escapes(value: str) -> bool:
    """True for an absolute path, one with ``..``, or an empty one."""
    p = PurePosixPath(value.replace("\\", "/"))
    return p.is_absolute() or value[1:3] == ":/" or ".." in p.parts or not value.strip()


def relative_path(value: str) -> str:
    """A path that stays below the folder it is resolved against: relative, no ``..``."""
    if _escapes(value):
        raise ValueError(f"must be a relative path inside the experiment's folder (no absolute path, no ..), "
                         f"got {value!r}")
    return value


def urdf_name(value: str) -> str:
    """A URDF file under ``assets/urdf`` (built-in robots), in the experiment's folder or, spelled
    ``pybullet_data:<path>``, in the installed pybullet_data (``pybullet_urdf``): no absolute path, no ``..``."""
    if _escapes(value):
        raise ValueError("must name a file under assets/urdf (built-in robots) or in the experiment's folder "
                         "(pybullet_urdf; or pybullet_data:<path> for a file of the installed pybullet_data): "
                         f"no absolute path, no .., got {value!r}")
    return value


class Section(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)


class InputGrid(Section):
    lo: list[Finite]
    hi: list[Finite]
    counts: list[Int1]


class SystemSection(Section):
    """``[system]``: a built-in system by name or a refined-system .json (in the experiment's
    folder); its input set as a list or a grid."""
    name: str
    steps: Steps = 1
    inputs: Optional[Union[list[list[Finite]], list[Finite]]] = None
    input_grid: Optional[InputGrid] = None

    @model_validator(mode="after")
    def _one_input_set(self):
        if self.inputs is not None and self.input_grid is not None:
            raise ValueError("give inputs or input_grid, not both")
        return self


class SimulatorOptions(BaseModel):
    """``[simulator.options]``: simulator-specific (each simulator checks its own); the URDF is
    a file name under ``assets/urdf`` (built-in robots) or in the experiment's folder
    (``pybullet_urdf``, confined on loading), never a path elsewhere."""
    model_config = ConfigDict(extra="allow", strict=True)
    urdf: Optional[Annotated[str, AfterValidator(urdf_name)]] = None


class SimulatorSection(Section):
    """``[simulator]``: see :mod:`simgap.simulators`."""
    kind: str
    noise: dict[str, Any] = {}
    randomize: dict[str, Any] = {}
    effects: dict[str, Any] = {}
    options: SimulatorOptions = SimulatorOptions()
    system: Optional[str] = None
    steps: Optional[Steps] = None


class CollectSection(Section):
    """``[collect]``: the cover, N1hat, the seed, chunking and where to run (:mod:`simgap.collect`).

    ``epsilon``: the cover radius, or one radius per covered dimension (a grid of spacing 2 eps_j,
    Euclidean radius ||eps||; not together with ``spacing``)."""
    epsilon: Union[Positive, list[Positive]]
    n_runs: Annotated[int, Field(ge=2, description="N1hat")]
    seed: Int0 = 0
    spacing: Optional[list[Positive]] = None
    invariant_dims: list[Union[str, Int0]] = []
    fixed: dict[str, Finite] = {}
    region: dict[str, Annotated[list[Finite], Field(min_length=2, max_length=2)]] = {}
    # a cover along the box tube (simgap.tube_cover): the room beyond the nominal tube, one value or one per state
    tube_margin: Optional[Union[Positive, list[Positive]]] = None
    # anytime-valid rounds (simgap.rounds): what the rounds after the first may spend
    budget_runs: Optional[Int1] = None
    budget_minutes: Optional[Positive] = None
    chunk_size: Optional[Int1] = None
    batch_runs: Int1 = 1 << 18
    keep_samples: bool = False
    executor: Literal["serial", "local", "ray"] = "local"
    workers: Optional[Int0] = None
    address: Optional[str] = None
    out: Optional[Annotated[str, AfterValidator(relative_path)]] = None

    @model_validator(mode="after")
    def _radii(self):
        if isinstance(self.epsilon, list):
            if self.spacing is not None:
                raise ValueError("epsilon: give one radius per covered dimension or a spacing, not both")
            if not self.epsilon:
                raise ValueError("epsilon: an empty list (need one radius per covered dimension)")
            self.spacing = [2.0 * e for e in self.epsilon]
            # the Euclidean radius of the grid's cells, a hair above so that rounding cannot refuse it
            self.epsilon = float(sum(e * e for e in self.epsilon) ** 0.5) * (1 + 1e-12)
        return self


class CertifySection(Section):
    """``[certify]``: :class:`simgap.certify.CertifyOptions` (``terms`` keys: a state name or ``all``, as on the
    command line; or a 0-based dimension, -1 = all)."""
    degree: Union[Annotated[int, Field(ge=-1)], list[Annotated[int, Field(ge=-1)]]] = 2
    terms: dict[str, list[str]] = {}
    delta1: Optional[Union[Positive, list[Positive]]] = None
    delta2: Optional[Union[Positive, list[Positive]]] = None
    beta1: Optional[Union[Probability, list[Probability]]] = None
    beta2: Optional[Union[Probability, list[Probability]]] = None
    confidence: Optional[Annotated[float, Field(gt=0, lt=1)]] = None
    variance: Literal["empirical", "maurer_pontil"] = "empirical"
    safety: Positive = 10.0
    value_range: Optional[Positive] = None
    concentration: Literal["chebyshev", "bernstein", "subgaussian"] = "chebyshev"
    uniform: bool = False
    lemma2_factor: Literal[2.0, 4.0] = 2.0
    lipschitz_mode: Literal["increment", "state"] = "increment"
    l2: Literal["analytic", "estimated"] = "analytic"
    lhat: Literal["data", "simulator"] = "data"
    lhat_pairs: Int1 = 2000
    lhat_runs: Annotated[int, Field(ge=2)] = 100
    lipschitz_term: Literal["paper", "gap"] = "paper"
    continuous_inputs: bool = False
    solver: Literal["CLARABEL", "HIGHS"] = "CLARABEL"
    seed: Int0 = 0

    @model_validator(mode="after")
    def _term_keys(self):
        for k in self.terms:  # state names are checked against the system (simgap.certify.basis.term_dimension)
            try:
                bad = int(k) < -1
            except ValueError:
                bad = not str(k).isidentifier()
            if bad:
                raise ValueError(f"terms: keys are state names, all, or 0-based state dimensions (-1 = all), "
                                 f"got {k!r}")
        return self


class AuditSection(Section):
    """``[audit]``: fresh (x, u) points and simulator runs per point."""
    points: Int1 = 200
    runs: Annotated[int, Field(ge=2)] = 2000
    seed: Int0 = 7


class SynthesisSection(Section):
    """``[synthesis]``: the specification, grid cell widths eta, and the input hold; with
    ``method = "invariant_set"`` a linear feedback on a proved ellipsoid instead of the grid
    (equilibrium ``x_star``/``u_star`` and gain ``K`` optional, LQR weights ``lqr_q``/``lqr_r``,
    cvxpy ``solver``, ``set_states`` states drawn in E for extra rollouts, ``nominal`` also
    synthesizes on the nominal model without a gap); with ``method = "box_tube"`` a time-varying
    feedback on a proved box tube from [rollout] x0 to a box around x* (``target_lo``/``target_hi``,
    ``shells`` pieces of the mean-value form, ``input_margin`` kept for the feedback along the plan,
    ``margin_search`` the tolerable-gap search, ``per_run`` the per-run statement of the noise tube, ``plan_input_weight`` the plan's pace;
    docs/synthesis.md)."""
    spec: Literal["invariance", "reach_avoid"] = "invariance"
    method: Literal["grid", "invariant_set", "box_tube"] = "grid"
    eta: Optional[Union[Positive, list[Positive]]] = None
    hold: Int1 = 1
    safe_lo: Optional[list[Finite]] = None
    safe_hi: Optional[list[Finite]] = None
    map: Optional[str] = None
    x_star: Optional[list[Finite]] = None
    u_star: Optional[list[Finite]] = None
    K: Optional[list[list[Finite]]] = None
    K_plan: Optional[list[list[Finite]]] = None
    lqr_q: Optional[list[Positive]] = None
    lqr_r: Optional[list[Positive]] = None
    solver: Literal["CLARABEL", "SCS"] = "CLARABEL"
    set_states: Int0 = 20
    nominal: bool = True
    target_lo: Optional[list[Finite]] = None
    target_hi: Optional[list[Finite]] = None
    shells: Int1 = 16
    input_margin: Annotated[float, Field(ge=0.0, lt=1.0)] = 0.3
    margin_search: bool = True
    terminal: Literal["largest", "smallest"] = "largest"
    per_run: bool = True
    plan_input_weight: Optional[Positive] = None


class RolloutSection(Section):
    """``[rollout]``: closed-loop rollouts in the stochastic simulator."""
    n: Int1 = 1000
    horizon: Optional[Int1] = None
    x0: Optional[list[Finite]] = None
    seed: Int0 = 11
    on_exit: Literal["hold", "stop"] = "hold"


class PerrunSection(Section):
    """``[perrun]``: the per-run stage (:mod:`simgap.perrun.stage`; its ``check_section`` checks
    the ranges against the data, e.g. the smallest alpha N1hat supports)."""
    alpha: float = 0.05
    beta: float = 0.01
    eta: Optional[Union[Positive, list[Positive]]] = None
    hold: int = 20
    n_runs: int = 2000
    pilot_runs: int = 200
    horizon: Optional[int] = None
    n_rollouts: int = 10000
    n_states: int = 20
    seed: Int0 = 0
    baseline_eta: Optional[Union[Positive, list[Positive]]] = None
    baseline_hold: Optional[Int1] = None
    split: Optional[list[Finite]] = None
    invariant: Optional[list[str]] = None
    share: Optional[Union[Int1, list[Int1]]] = None


class Experiment(Section):
    """A whole experiment (the base configuration with one profile merged in)."""
    description: str = ""
    system: SystemSection
    simulator: SimulatorSection
    collect: CollectSection
    certify: CertifySection = CertifySection()
    audit: AuditSection = AuditSection()
    synthesis: SynthesisSection = SynthesisSection()
    rollout: RolloutSection = RolloutSection()
    perrun: Optional[PerrunSection] = None


SECTIONS = [name for name in Experiment.model_fields if name != "description"]


def _model_at(loc: tuple):
    """The model class whose field set ``loc[-1]`` belongs to (for the nearest-name hint)."""
    model = Experiment
    for part in loc[:-1]:
        f = getattr(model, "model_fields", {}).get(part)
        if f is None:
            return None
        models = [a for a in (f.annotation, *get_args(f.annotation)) if isinstance(a, type) and issubclass(a, BaseModel)]
        if not models:
            return None
        model = models[0]
    return model


def nearest(name: str, candidates) -> Optional[str]:
    m = difflib.get_close_matches(str(name), list(candidates), n=1, cutoff=0.6)
    return m[0] if m else None


def _is_tag(part) -> bool:
    """pydantic's names of union alternatives and validators inside an error location."""
    return isinstance(part, str) and (any(c in part for c in "[(-") or part in ("int", "float", "str", "bool"))


def _clean(loc) -> tuple:
    return tuple(p for p in loc if not _is_tag(p))


def _key_text(loc: tuple) -> str:
    out = ""
    for p in loc:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out


def _describe(err: dict, origin) -> str:
    loc = _clean(err["loc"])
    typ = err["type"]
    msg = err["msg"].removeprefix("Value error, ")
    msg = msg[:1].lower() + msg[1:]
    if typ == "extra_forbidden":
        model = _model_at(loc)
        names = list(model.model_fields) if model is not None else []
        guess = nearest(loc[-1], names)
        if len(loc) == 1:
            hint = f"; did you mean [{guess}]?" if guess else ""  # (profiles: check_profiles)
            return f"unknown section [{loc[0]}]{hint} (sections: {', '.join(SECTIONS)})"
        hint = f"; did you mean {guess!r}?" if guess else ""
        return f"unknown key {loc[-1]!r} in [{origin(loc)}]{hint} (keys: {', '.join(names)})"
    if typ == "missing":
        return f"missing section [{loc[0]}]" if len(loc) == 1 else f"[{origin(loc[:-1])}] needs {_key_text(loc[1:])}"
    if len(loc) == 1:
        what = f"[{origin(loc)}]" if loc[0] in SECTIONS else loc[0]
    else:
        what = f"[{origin(loc[:2])}] {_key_text(loc[1:])}"
    if loc[-1:] == ("n_runs",):
        what += " (N1hat)"
    got = "" if typ == "value_error" or isinstance(err.get("input"), dict) else f", got {err.get('input')!r}"
    fix = _FIX.get(typ)
    if fix:  # a value of the wrong type: say how to write the right one (never guessed from a string)
        key = next((p for p in reversed(loc) if isinstance(p, str)), "key")
        return f"{what}: {msg}{got}; write " + spelling(key, fix)
    return f"{what}: {msg}{got}"


#: pydantic's type errors -> the typed.SPELLING kind of the fix
_FIX = {"bool_type": "bool", "int_type": "int", "float_type": "number", "string_type": "name"}


def validate(raw: dict, where: str, origin=lambda loc: loc[0]) -> Experiment:
    """Check one merged experiment table; SimgapError naming the problems (at most 5).

    ``origin(loc)`` names the table the key at ``loc`` (section, key, ...) was written in:
    the section, or e.g. ``profiles.small.collect`` when a profile set it.
    """
    try:
        return Experiment.model_validate(raw)
    except ValidationError as e:
        # a union (number or list) reports one error per alternative: per key keep the one
        # about a list element if there is one, else the first
        groups: dict = {}
        for err in e.errors():
            loc = _clean(err["loc"])
            key = tuple(p for p in loc if isinstance(p, str))[:2]
            if key not in groups or (any(isinstance(p, int) for p in loc)
                                     and not any(isinstance(p, int) for p in _clean(groups[key]["loc"]))):
                groups[key] = err
        lines = [_describe(err, origin) for err in groups.values()]
        more = f" (and {len(lines) - 5} more)" if len(lines) > 5 else ""
        raise SimgapError(f"{where}: " + "; ".join(lines[:5]) + more) from None


def check_profiles(profiles: Any, where: str) -> None:
    """``[profiles.<name>.<section>]`` tables only, with known section names."""
    if not isinstance(profiles, dict):
        raise SimgapError(f"{where}: [profiles] must hold tables [profiles.<name>.<section>]")
    for name, prof in profiles.items():
        if not isinstance(prof, dict):
            raise SimgapError(f"{where}: profiles.{name} must be a table of sections")
        for sec, body in prof.items():
            if sec not in SECTIONS:
                guess = nearest(sec, SECTIONS)
                raise SimgapError(f"{where}: unknown section [profiles.{name}.{sec}]"
                                  + (f"; did you mean [profiles.{name}.{guess}]?" if guess else "")
                                  + f" (sections: {', '.join(SECTIONS)})")
            if not isinstance(body, dict):
                raise SimgapError(f"{where}: [profiles.{name}.{sec}] must be a table, got {body!r}")
