"""The result of a rollout run: arrays, the JSON summary, files (npz without pickle).

A rollout file records ``digest``, the sha256 of its metadata (without the digest) and of every
array (:func:`simgap.fileio.content_digest`); :func:`load_rollout` recomputes it and refuses a file
whose content no longer matches (e.g. its ``controller_digest`` edited to another controller's, which
would draw the rollouts as that controller's), a file without a digest, and non-finite states."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from .. import fileio
from ..errors import BAD_FILE_ERRORS, SimgapError
from ..synthesis.spec import Spec
from .judge import OUTCOMES, SUCCESS, VIOLATION_KINDS, judge_path


def _json_safe(v):
    """Replace non-finite floats by strings so the summary is strict JSON (Box.from_dict reads them)."""
    if isinstance(v, dict):
        return {k: _json_safe(w) for k, w in v.items()}
    if isinstance(v, (list, tuple)):
        return [_json_safe(w) for w in v]
    if isinstance(v, float) and not np.isfinite(v):
        return "nan" if np.isnan(v) else ("inf" if v > 0 else "-inf")
    return v


def _stats(t: np.ndarray, tau: float) -> Optional[dict]:
    if t.size == 0:
        return None
    return {"count": int(t.size), "min": int(t.min()), "mean": float(t.mean()), "median": float(np.median(t)),
            "max": int(t.max()), "mean_s": float(t.mean() * tau), "max_s": float(t.max() * tau)}


@dataclass
class RolloutResult:
    """R closed-loop rollouts from one x0 plus the nominal-model run (module docstring: semantics).

    Arrays (R rollouts, T = horizon simulator steps, n states)
    ----------------------------------------------------------
    trajectories : (R, T+1, n)   states; after a rollout stopped, its last state repeats
    lengths : (R,)               index of each rollout's last real state
    outcome : (R,) int8          code into OUTCOMES (success, violation, timeout, left_domain)
    success : (R,) bool          the specification held
    violation_time : (R,)        first violating step, -1 if none
    violation_kind : (R,) int8   code into VIOLATION_KINDS (none, obstacle, outside_X, unsafe)
    reach_time : (R,)            step of reaching the target, -1 if never (reach-avoid)
    left_domain_time : (R,)      first query outside the winning domain, -1 if never
    input_index : (R, T) int32   applied input (row of system.inputs), -1 after stopping (an
                                 invariant-set controller: 0 = its feedback law u* + K (x - x*))
    mean_trajectory : (T+1, n)   the rollout average: mean over the R rollouts (circular mean
                                 for angles); NOT the sequence the guarantee is about
    nominal_trajectory : (T+1, n) the nominal model's closed loop (same padding rule)
    mean_map_trajectory : (T+1, n) or None   m+ = E fhat(m, u(m)) from the current mean
                                 (:mod:`simgap.rollout.mean_map`): what the guarantee is about;
                                 ``mean_map`` holds its outcome, runs per step and standard errors
    """

    x0: np.ndarray
    trajectories: np.ndarray
    lengths: np.ndarray
    outcome: np.ndarray
    violation_time: np.ndarray
    violation_kind: np.ndarray
    reach_time: np.ndarray
    left_domain_time: np.ndarray
    input_index: np.ndarray
    mean_trajectory: np.ndarray
    nominal_trajectory: np.ndarray
    nominal: dict
    spec: Spec
    tau: float
    hold: int
    horizon: int
    seed: Optional[int]
    on_exit: str
    system: str
    simulator: dict = field(default_factory=dict)
    timing: dict = field(default_factory=dict)
    mean_map_trajectory: Optional[np.ndarray] = None
    mean_map: Optional[dict] = None
    controller_digest: Optional[str] = None  # the content digest of the controller file rolled out

    @property
    def n_rollouts(self) -> int:
        return int(self.trajectories.shape[0])

    @property
    def success(self) -> np.ndarray:
        return self.outcome == SUCCESS

    @property
    def n_failures(self) -> int:
        return int(np.count_nonzero(self.outcome != SUCCESS))

    @property
    def rollout_average_verdict(self) -> dict:
        """The spec judged on the rollout average (not the guarantee's sequence: see ``mean_map``)."""
        return judge_path(self.spec, self.mean_trajectory, *self._x_bounds())

    def _x_bounds(self):
        return np.asarray(self.nominal["x_lo"]), np.asarray(self.nominal["x_hi"])

    def to_dict(self, per_rollout: bool = True) -> dict:
        """JSON-ready summary (strict JSON: infinities written as strings)."""
        counts = {name: int(np.count_nonzero(self.outcome == i)) for i, name in enumerate(OUTCOMES)}
        kinds = {name: int(np.count_nonzero(self.violation_kind == i)) for i, name in enumerate(VIOLATION_KINDS) if i}
        reached = self.reach_time[self.reach_time >= 0]
        d = {
            "system": self.system, "simulator": self.simulator, "spec": self.spec.to_dict(),
            "x0": self.x0.tolist(), "n_rollouts": self.n_rollouts, "horizon": self.horizon,
            "hold": self.hold, "tau": self.tau, "seed": self.seed, "on_exit": self.on_exit,
            "failures": self.n_failures, "successes": counts["success"], "outcomes": counts,
            "violation_kinds": kinds,
            "left_domain": int(np.count_nonzero(self.left_domain_time >= 0)),
            "reach_time_steps": _stats(reached, self.tau),
            "violation_time_steps": _stats(self.violation_time[self.violation_time >= 0], self.tau),
            "nominal": {k: v for k, v in self.nominal.items() if k not in ("x_lo", "x_hi")},
            "mean_map": self.mean_map,
            "rollout_average": self.rollout_average_verdict,
            "timing": self.timing,
            "controller_digest": self.controller_digest,
        }
        if per_rollout:
            d["per_rollout"] = {"outcome": [OUTCOMES[int(o)] for o in self.outcome],
                                "violation_time": self.violation_time.tolist(),
                                "violation_kind": [VIOLATION_KINDS[int(k)] for k in self.violation_kind],
                                "reach_time": self.reach_time.tolist(),
                                "left_domain_time": self.left_domain_time.tolist()}
        return _json_safe(d)

    def summary_lines(self) -> list:
        """Human-readable summary table (the CLI prints it)."""
        d = self.to_dict(per_rollout=False)
        R = self.n_rollouts
        lines = [f"{R} rollouts of {self.system} from x0 = {np.round(self.x0, 4).tolist()}, "
                 f"horizon {self.horizon} steps x {self.tau:g} s, input held {self.hold} step(s), seed {self.seed}",
                 f"  spec held       {d['successes']:>6d} / {R}",
                 f"  failures        {d['failures']:>6d} / {R}   "
                 + ", ".join(f"{k} {v}" for k, v in d["outcomes"].items() if k != "success" and v),
                 "  violations      " + (", ".join(f"{k} {v}" for k, v in d["violation_kinds"].items() if v) or "none"),
                 f"  left win. dom.  {d['left_domain']:>6d} / {R}   (on_exit={self.on_exit})"]
        rt = d["reach_time_steps"]
        if rt:
            lines.append(f"  reach time      min {rt['min']}  mean {rt['mean']:.1f}  median {rt['median']:.0f}  "
                         f"max {rt['max']} steps  (mean {rt['mean_s']:.3f} s)")
        nm = d["nominal"]
        lines.append(f"  nominal model   {nm['outcome']}" + (f", reach step {nm['reach_time']}" if nm["reach_time"] >= 0 else "")
                     + (f", violation step {nm['violation_time']} ({nm['violation_kind']})" if nm["violation_time"] >= 0 else ""))
        mm = self.mean_map
        if mm is None:
            lines.append("  mean map        not computed (mean_map_runs = 0)")
        else:
            lines.append(f"  mean map        {mm['outcome']}" + (f", reach step {mm['reach_time']}" if mm["reach_time"] >= 0 else "")
                         + (f", violation step {mm['violation_time']} ({mm['violation_kind']})" if mm["violation_time"] >= 0 else "")
                         + f": m+ = E fhat(m, u(m)), {mm['runs_per_step']} runs per step, std. error <= ["
                         + ", ".join(f"{v:.2g}" for v in mm["max_std_error"])
                         + ("] propagated over " + f"{mm['groups']} groups (one-step: <= ["
                            + ", ".join(f"{v:.2g}" for v in mm["max_step_std_error"]) + "])"
                            if "groups" in mm else "] (one step, conditional)")
                         + " (the sequence the guarantee is about; Theorem 1 rows: "
                         + mm.get("theorem1_rows", "not recorded") + ")")
        mv = d["rollout_average"]
        lines.append(f"  rollout average {'satisfies' if mv['satisfied'] else 'violates'} the spec"
                     + (f" (reach step {mv['reach_time']})" if mv["reach_time"] >= 0 else "")
                     + f" (mean of the {R} rollouts; not what the guarantee is about)")
        tm = self.timing
        if tm:
            total = tm.get("total_wall_s")
            if total is not None:  # the wall time of everything done, the mean map's runs included
                lines.append(f"  time            {total:.2f} s wall in all: rollouts {tm['wall_s']:.2f} s, mean map "
                             f"{tm.get('mean_map_s', 0):.2f} s")
            lines.append(f"  rollouts        {tm['wall_s']:.2f} s ({tm.get('cpu_s', 0):.2f} s CPU), {tm['robot_steps']} robot-steps, "
                         f"{tm['robot_steps_per_s']:.0f} robot-steps/s ({'batched' if tm['batched'] else 'one at a time'})")
        return lines

    # ----- files --------------------------------------------------------------------------
    def save_npz(self, path) -> None:
        """Write all arrays and the JSON summary to ``path`` (temp file + rename; no pickle)."""
        arrays = {k: getattr(self, k) for k in ("x0", "trajectories", "lengths", "outcome", "violation_time",
                                                "violation_kind", "reach_time", "left_domain_time",
                                                "input_index", "mean_trajectory", "nominal_trajectory")}
        if self.mean_map_trajectory is not None:
            arrays["mean_map_trajectory"] = self.mean_map_trajectory
        meta = self.to_dict(per_rollout=False)
        meta["nominal_full"] = _json_safe(self.nominal)
        meta = json.loads(json.dumps(meta))  # the digest is of the metadata as a reader will see it
        meta["digest"] = fileio.content_digest(meta, arrays)
        arrays["meta_json"] = np.array(json.dumps(meta))
        path = os.fspath(path)
        fileio.savez(path if path.endswith(".npz") else path + ".npz", compressed=True, **arrays)

    def save_json(self, path, per_rollout: bool = True) -> None:
        """Write :meth:`to_dict` as JSON (temp file + rename)."""
        fileio.write_json(path, self.to_dict(per_rollout=per_rollout))


def load_rollout(path) -> RolloutResult:
    """Read a file written by :meth:`RolloutResult.save_npz` (no pickle)."""
    from ..file_guard import loads_json, regular_file
    regular_file(path, "rollout file")
    try:
        with np.load(os.fspath(path), allow_pickle=False) as z:
            a = {k: z[k] for k in z.files}
    except BAD_FILE_ERRORS as e:
        raise SimgapError(f"rollout file {str(path)!r}: cannot read ({e})") from None
    if "meta_json" not in a:
        raise SimgapError(f"rollout file {str(path)!r}: not a simgap rollout file (no meta_json)")
    meta = loads_json(str(a.pop("meta_json")), f"rollout file {str(path)!r}: its metadata")
    if not isinstance(meta, dict):
        raise SimgapError(f"rollout file {str(path)!r}: its metadata is not a table (not a simgap rollout file)")
    want = meta.pop("digest", None)
    if want is None:
        raise SimgapError(f"rollout file {str(path)!r} records no content digest (written before rollout files "
                          "carried one, or not by simgap): roll out again (refused)")
    have = fileio.content_digest(meta, a)
    if have != want:
        raise SimgapError(f"rollout file {str(path)!r} was modified after it was written (refused): its content "
                          f"digest is {have[:16]}... but the file records {str(want)[:16]}...")
    for name in ("x0", "trajectories", "mean_trajectory", "nominal_trajectory", "mean_map_trajectory"):
        if name in a and a[name].dtype.kind in "fc" and not np.all(np.isfinite(a[name])):
            bad = int((~np.isfinite(a[name])).sum())
            raise SimgapError(f"rollout file {str(path)!r}: {name} holds {bad} NaN or infinite value(s); a simulator "
                              "never returns them (simgap refuses such a step), so the file was not written by a "
                              "rollout (refused)")
    try:
        return _result(a, meta)
    except (KeyError, TypeError, ValueError) as e:
        raise SimgapError(f"rollout file {str(path)!r}: its metadata lacks or mistypes {e} (refused)") from None


def _result(a: dict, meta: dict) -> RolloutResult:
    nominal = meta["nominal_full"]
    nominal["x_lo"] = [float(v) for v in nominal["x_lo"]]
    nominal["x_hi"] = [float(v) for v in nominal["x_hi"]]
    return RolloutResult(**a, nominal=nominal, spec=Spec.from_dict(meta["spec"]), tau=meta["tau"], hold=meta["hold"],
                         horizon=meta["horizon"], seed=meta["seed"], on_exit=meta["on_exit"], system=meta["system"],
                         simulator=meta["simulator"], timing=meta["timing"], mean_map=meta.get("mean_map"),
                         controller_digest=meta.get("controller_digest"))

