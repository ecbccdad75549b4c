"""The box-tube controller: u_t(x) = u_nom(t) + K (x - x_nom(t)) for t < T0, u* + K (x - x*) after.

A time-varying controller (``time_varying = True``): rollouts and the mean map pass the period
``t`` (controller periods since x0) to ``input``, ``input_index`` and ``winning``. Its set at t
is the proved box x_nom(t) +- h_t for t <= T0, then the terminal box x* +- H
(:mod:`simgap.synthesis.box_tube`). The boxes bound the MEAN state (the paper's Theorem 1); a
single noisy run may leave them, so the law is applied at every state (``input_index`` is always 0,
``input(strict=False)`` never NaN): a run that left the tube gets the feedback, not a held input.

File format (``.npz``, no pickle; :mod:`.controller_file`): arrays ``x_nom`` (T0 + 1, n),
``u_nom`` (T0, m), ``K`` (m, n), ``x_star`` (n,), ``u_star`` (m,), ``H`` (n,), ``radii``
(T0 + 1, n), and ``meta`` (kind ``box_tube``, the proof's statistics, the gap's provenance, x0,
the margin, the digest); with a per-run statement (:mod:`.noise_tube`) also ``noise_radii``
(T0 + 1, n) and ``noise_H`` (n,), its numbers in ``meta["noise_tube"]``. :meth:`from_arrays` recomputes the digest and refuses an edited file.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import BAD_FILE_ERRORS, SimgapError
from ..sets import Box
from ..systems import System
from .controller_file import check_digest, write_controller
from .noise_tube import NoiseTube
from .spec import Spec
from .statement import DrawnSet, PerRunStatement, Row, Statement, fmt_list, gap_words, margin_words

KIND = "box_tube"
ARRAYS = ("x_nom", "u_nom", "K", "x_star", "u_star", "H", "radii")
#: the per-run statement's tube, when there is one
NOISE_ARRAYS = ("noise_radii", "noise_H")
#: relative slack of the membership test (the tube at t = 0 is the single point x0)
TOL = 1e-9


class TubeController:
    """A time-varying linear feedback on a proved box tube (module docstring)."""

    continuous_input = True
    time_varying = True
    kind = KIND

    def __init__(self, plan, radii, system: Optional[System] = None, spec: Optional[Spec] = None,
                 meta: Optional[dict] = None, hold: int = 1, noise_tube: Optional[NoiseTube] = None):
        self.x_nom = np.asarray(plan.x_nom, dtype=float)
        n = self.x_nom.shape[1]
        self.K = np.asarray(plan.K, dtype=float).reshape(-1, n)
        m = self.K.shape[0]
        self.u_nom = np.asarray(plan.u_nom, dtype=float).reshape(-1, m)
        self.x_star = np.asarray(plan.x_star, dtype=float).ravel()
        self.u_star = np.asarray(plan.u_star, dtype=float).ravel()
        self.H = np.asarray(plan.H, dtype=float).ravel()
        self.radii = np.asarray(radii, dtype=float).reshape(self.x_nom.shape)
        if hold != 1:  # a file edited with its digest recomputed must not hold the input longer than the proof
            raise SimgapError(f"box-tube controller: hold = {hold!r}, but its proof applies u(x) every period (hold = 1): "
                              "refused (was the file edited?)")
        self.system, self.spec, self.hold = system, spec, int(hold)
        self.meta = dict(meta or {})
        self.noise_tube = noise_tube
        if noise_tube is not None:
            self.meta["noise_tube"] = {k: v for k, v in noise_tube.to_dict().items() if k not in ("H", "max_radius")}
        x0 = self.meta.get("x0")
        self.x0 = self.x_nom[0].copy() if x0 is None else np.asarray(x0, dtype=float)

    @property
    def T0(self) -> int:
        return int(self.u_nom.shape[0])

    @property
    def size(self) -> int:
        return 1

    size_with_target = size

    # ----- the sets -------------------------------------------------------------------
    def box_at(self, t: int, noise: bool = False) -> Box:
        """The proved box at period t (the tube's for t <= T0, the terminal box after); with ``noise``
        the per-run statement's (SimgapError without one)."""
        t = int(t)
        if t < 0:
            raise SimgapError(f"box tube: period t must be >= 0, got {t}")
        radii, H = self._sets(noise)
        if t <= self.T0:
            return Box(self.x_nom[t], radii[t])
        return Box(self.x_star, H)

    def _sets(self, noise: bool):
        """(radii, H) of the mean's tube or (``noise``) of the per-run statement's."""
        if not noise:
            return self.radii, self.H
        if self.noise_tube is None:
            raise SimgapError("this box-tube controller carries no per-run statement (no noise tube)")
        return self.noise_tube.radii, self.noise_tube.H

    @property
    def terminal_box(self) -> Box:
        return Box(self.x_star, self.H)

    def winning(self, x, t: int = 0) -> np.ndarray:
        """(B,) bool: x lies in the proved box at period t."""
        b = self.box_at(t)
        x = np.atleast_2d(np.asarray(x, dtype=float))
        return np.all(np.abs(x - b.c) <= b.r + TOL * (1.0 + np.abs(b.c)), axis=-1)

    def check_winning(self, x, what: str = "initial state", t: int = 0) -> None:
        x = np.atleast_2d(np.asarray(x, dtype=float))
        ok = self.winning(x, t)
        if not ok.all():
            i = int(np.flatnonzero(~ok)[0])
            b = self.box_at(t)
            raise SimgapError(f"{what} {x[i].tolist()} is outside the box tube at period {t} (centre "
                              f"{np.round(b.c, 6).tolist()}, half-widths {np.round(b.r, 6).tolist()}); the tube "
                              f"starts at x0 = {self.x0.tolist()}")

    def reached_and_stayed(self, traj) -> np.ndarray:
        """(R,) bool: trajectories (R, T + 1, n) (period 0 = x0) inside the terminal box at every
        period from T0 on (True when they end before T0)."""
        traj = np.asarray(traj, dtype=float)
        tail = traj[:, self.T0:]
        return np.all(np.abs(tail - self.x_star) <= self.H + TOL * (1.0 + np.abs(self.x_star)), axis=(1, 2))

    def steps_to_go(self, x) -> np.ndarray:
        """(B,) T0: the periods the plan needs (rollouts default to twice this plus one)."""
        return np.full(np.atleast_2d(x).shape[0], float(self.T0))

    # ----- inputs ---------------------------------------------------------------------
    def input(self, x, strict: bool = True, t: int = 0) -> np.ndarray:
        """(B, m) u_t(x). With ``strict``, SimgapError for a state outside the box at t; without, the
        law at every state (the tube bounds the MEAN state; a single noisy run may leave it and still
        gets the feedback, never a held input)."""
        x = np.atleast_2d(np.asarray(x, dtype=float))
        if strict:
            self.check_winning(x, "state", t)
        t = int(t)
        if t < self.T0:
            return self.u_nom[t] + (x - self.x_nom[t]) @ self.K.T
        return self.u_star + (x - self.x_star) @ self.K.T

    def input_index(self, x, t: int = 0) -> np.ndarray:
        """(B,) 0: the feedback law applies at every state (see :meth:`input`; membership of the proved
        boxes is :meth:`winning`, of whole trajectories :meth:`inside`)."""
        return np.zeros(np.atleast_2d(x).shape[0], dtype=np.int64)

    def inside(self, traj, noise: bool = False) -> np.ndarray:
        """(R,) bool: trajectories (R, T + 1, n) (period 0 = x0) inside the proved box of every period:
        the mean's tube, or with ``noise`` the per-run statement's wider tube (SimgapError without one)."""
        radii, H = self._sets(noise)
        traj = np.asarray(traj, dtype=float)
        T = traj.shape[1]
        c = np.concatenate([self.x_nom[:T], np.repeat(self.x_star[None], max(0, T - self.T0 - 1), axis=0)])
        r = np.concatenate([radii[:T], np.repeat(H[None], max(0, T - self.T0 - 1), axis=0)])
        return np.all(np.abs(traj - c) <= r + TOL * (1.0 + np.abs(c)), axis=(1, 2))

    # ----- description ----------------------------------------------------------------
    def outlines(self, dims=(0, 1), every: int = 1, noise: bool = False) -> list:
        """Closed rectangles (5, 2) of the tube's boxes on two states (every ``every``-th period) and
        the terminal box last (figures and recordings); with ``noise`` the per-run statement's."""
        d = [int(i) for i in dims]
        out = [self.box_at(t, noise).project(d).outline((0, 1)) for t in range(0, self.T0 + 1, max(1, int(every)))]
        return out + [self.box_at(self.T0 + 1, noise).project(d).outline((0, 1))]

    def projection_outline(self, dims, points: int = 0) -> np.ndarray:
        """The terminal box's rectangle on two states (what figures draw for a set controller)."""
        return self.terminal_box.project([int(i) for i in dims]).outline((0, 1))

    def describe(self) -> dict:
        return {"kind": KIND, "n": int(self.x_star.size), "m": int(self.u_star.size), "hold": self.hold,
                "T0": self.T0, "x_star": self.x_star.tolist(), "u_star": self.u_star.tolist(),
                "H": self.H.tolist(), "margins": self.meta.get("margins")}

    def summary(self) -> str:
        st = self.meta.get("stats", {})
        return (f"box-tube controller: u = u_nom(t) + K (x - x_nom(t)) for {self.T0} periods, then u* + K (x - x*); "
                f"K = {np.round(self.K, 4).tolist()}, x* = {self.x_star.tolist()}; terminal box half-widths "
                f"{np.round(self.H, 6).tolist()}; {margin_words(st)}")

    def statement(self, entry: Optional[dict] = None):
        """What the box tube proved, in its words (:mod:`.statement`); ``entry``: the method's record in
        summary.json (its rollouts' counts and p_cert at their horizon), optional."""
        entry = entry or {}
        st = self.meta.get("stats", {})
        gw = gap_words(self.meta)
        nominal = (self.meta.get("gap") or {}).get("kind") == "none"
        conf = None if nominal or entry.get("confidence_proof") is None else "all rows"
        name = "box tube from x0 (reach and stay)"
        v = st.get("verification") or {}
        rows = [Row("proved", "yes: the tube from x0", "proof", conf),
                Row("plan T0 (periods to the terminal box)", str(self.T0), "proof", conf),
                Row("terminal box half-widths H", fmt_list(self.H), "proof", conf),
                Row("tube's largest half-widths", fmt_list(self.radii.max(axis=0)), "proof", conf)]
        if v.get("w_max") is not None:
            rows.append(Row("gap over the tube [max]", fmt_list(v["w_max"]), "proof", conf))
        rows += [Row("margin: the proof holds with gamma x", str(st.get("gap_scale_text", "-")), "proof", conf),
                 Row("feedback K", str(st.get("K_how", "-")).split(",")[0], "proof", conf)]
        nt_stats = st.get("noise_tube") or {}
        nt = self.noise_tube
        rows.append(Row("noise tube (single runs)", f"lam = {nt.lam:.3g} x the noise's proxy" if nt is not None else
                        f"none: {nt_stats.get('none', 'not asked for')}", "proof", conf))
        ras, pe = entry.get("reach_and_stay"), entry.get("per_run_empirical") or {}
        notes = []
        if ras is not None and ras.get("mean_map_in_tube") is not None:
            inside = bool(ras["mean_map_in_tube"])
            why = ("" if inside else
                   " (f's tube without a gap: no statement about the simulator's mean map)" if nominal else
                   " (the tube of a gap without noise, half-widths <= " + f"{self.radii.max():.3g}: no statement "
                   "about the noisy simulator's mean map)" if conf is None else
                   " (OUTSIDE the proved tube: possible only if the certificate is wrong, probability <= 1 - its "
                   "all-rows confidence)")
            rows.append(Row("mean map inside the tube", "yes" if inside else "no (see the note)" if why else "no",
                            "mean_map"))
            if why:
                notes.append("mean map inside the tube: no" + why)
        if ras is not None:
            rows += [Row("single runs reaching and staying in H", f"{ras['held']} / {ras['of']} after period "
                         f"{ras['T0']}", "single_runs"),
                     Row("single runs inside the mean's tube", f"{ras['runs_in_tube']} / {ras['of']}", "single_runs")]
        if "in_noise_tube" in pe:
            rows.append(Row("single runs inside the noise tube (p_cert's event)",
                            f"{pe['in_noise_tube']} / {pe['n_rollouts']}", "single_runs"))
        per_run = None
        if nt is not None:
            T = int(pe.get("horizon", nt.horizon))
            p = pe.get("p_cert") if pe.get("p_cert") is not None else nt.p_run(min(T, nt.horizon))
            per_run = PerRunStatement(
                p_cert=float(p), horizon=T,
                event=f"a run stays in the noise tube for {T} periods, then in its terminal box",
                rests_on=f"1 - beta_noise {nt.beta_noise(min(T, nt.horizon)):.3g} - beta_cert {nt.beta_cert:.3g}; "
                         f"assumes {nt.assumption}")
            rows.append(Row(f"p_cert per run ({T} periods)", f"{per_run.p_cert:.4f}", "per_run", conf))
        elif nt_stats.get("none"):
            notes.append(f"no per-run probability: {nt_stats['none']}")
        periods = np.arange(self.T0 + 2)

        def boxes(role, label, radii, H):
            return DrawnSet(role, label, "boxes", np.vstack([self.x_nom, self.x_star]), np.vstack([radii, H]),
                            periods)
        sets = [boxes("tube", "box tube (the mean map's, proved)", self.radii, self.H)]
        if nt is not None:
            sets.append(boxes("noise_tube", "noise tube (single runs, p_cert's event)", nt.radii, nt.H))
        sets.append(DrawnSet("terminal", "terminal box x* +- H", "boxes", self.x_star[None], self.H[None],
                             np.array([self.T0])))
        tgt = st.get("target")
        if tgt:
            lo, hi = np.asarray(tgt["lo"], float), np.asarray(tgt["hi"], float)
            sets.append(DrawnSet("target", "target box", "boxes", ((lo + hi) / 2)[None], ((hi - lo) / 2)[None],
                                 np.array([self.T0])))
        head = (f"{name}: proved with {gw}, {self.T0} periods to x* +- H, {margin_words(st)}"
                + (f"; p_cert {per_run.p_cert:.3g} per run" if per_run else ""))
        return Statement(method=KIND, name=name, proved=True, headline=head, set_name="the tube", rows=rows,
                         sets=sets, per_run=per_run, notes=notes)

    # ----- files ----------------------------------------------------------------------
    def save(self, path) -> Path:
        arrays = {k: getattr(self, k) for k in ARRAYS}
        if self.noise_tube is not None:
            arrays.update(noise_radii=self.noise_tube.radii, noise_H=self.noise_tube.H)
        return write_controller(path, self.meta, KIND, self.hold, self.system, self.spec, arrays)

    @classmethod
    def from_arrays(cls, path, z, meta: dict, system: Optional[System] = None) -> "TubeController":
        """Build from an open .npz whose meta says kind box_tube (called by Controller.load)."""
        names = ARRAYS + (NOISE_ARRAYS if meta.get("noise_tube") else ())
        try:
            arrays = {k: np.asarray(z[k], dtype=float) for k in names}
        except (*BAD_FILE_ERRORS, KeyError) as e:
            raise SimgapError(f"controller file {str(path)!r} is not a box-tube controller ({e})") from None
        check_digest(path, meta, arrays)
        xn, un, K, xs, us, H, radii = (arrays[k] for k in ARRAYS)
        ok = xn.ndim == 2 and radii.shape == xn.shape and K.ndim == 2 and K.shape[1] == xn.shape[1] \
            and un.shape == (xn.shape[0] - 1, K.shape[0]) and xs.shape == (xn.shape[1],) and H.shape == xs.shape \
            and us.shape == (K.shape[0],) and all(np.all(np.isfinite(a)) for a in arrays.values()) \
            and np.all(H >= 0) and np.all(radii >= 0)
        nt = None
        if ok and meta.get("noise_tube"):
            nr, nH, d = arrays["noise_radii"], arrays["noise_H"], meta["noise_tube"]
            try:
                nt = NoiseTube(lam=float(d["lam"]), sigma=np.asarray(d["sigma"], float), radii=nr, H=nH,
                               beta_cert=float(d["beta_cert"]), horizon=int(d["horizon"]),
                               assumption=str(d["assumption"]))
            except (KeyError, TypeError, ValueError) as e:
                raise SimgapError(f"controller file {str(path)!r}: its per-run statement is malformed ({e})") from None
            ok = nr.shape == radii.shape and nH.shape == H.shape and np.all(nr >= 0) and np.all(nH >= 0) \
                and nt.sigma.shape == H.shape and np.all(nt.sigma >= 0) and nt.lam > 0 and 0 <= nt.beta_cert <= 1 \
                and nt.horizon >= 1
        if not ok:
            raise SimgapError(f"controller file {str(path)!r}: the box-tube arrays do not fit together")
        spec = Spec.from_dict(meta["spec"]) if meta.get("spec") else None
        if system is None and meta.get("system"):
            from ..system_ref import ref_of_description, resolve_system
            try:
                system = resolve_system(ref_of_description(meta["system"]), int(meta["system"].get("steps", 1)),
                                        paths=False)
            except SimgapError:
                system = None
        from types import SimpleNamespace
        plan = SimpleNamespace(x_nom=xn, u_nom=un, K=K, x_star=xs, u_star=us, H=H)
        return cls(plan, radii, system=system, spec=spec, meta=meta, hold=meta.get("hold", 1), noise_tube=nt)
