"""Why the cart-pole's invariance winning domain is empty: the nominal model alone (no gap), on
several grids, and its two halves (pole only, cart only) on the same grids.

    python bench/cartpole_synthesis_probe.py              # the table of docs/case-studies.md (minutes)
    python bench/cartpole_synthesis_probe.py --only 4d    # one part: 4d, pole, cart or loop
    python bench/cartpole_synthesis_probe.py --only loop  # the inner-loop rows (about 6 min of CPU, 2.3 GB)

Every row synthesizes an invariance controller (stay in the box X given on the row) for the model
of assets/experiments/cartpole/cartpole.toml with ``gap=None``: if the nominal model wins no cell,
no certified gap can. ``k`` is the number of 0.02 s periods per abstraction step (input held),
``U`` the number of ctrl values in [-3, 3]. The pole-only model is the (theta, omega) part of the
same right-hand side (it does not depend on p or v); the cart-only model is the double integrator
p'' = 100 u / (M + m) (the pole's reaction left out).

The ``loop`` rows put a fixed inner loop under the abstraction, as SCOTS users do with unstable
plants: the actuator receives ctrl = clip(u + 2.034 theta + 2.297 omega, -3, 3), computed from the
state at the start of each 0.02 s period and held, and the abstraction chooses the offset u from 5
values in [-0.5, 0.5] (|ctrl| <= 3 on X, so the clip is never active). The gains make the pole's
part (theta, omega) as contracting as a box can be (the optimum of max_i (|A_cl| h)_i / h_i over PD
gains). Because f does not depend on p, the (theta, v, omega) model without p is exact for those
three states; rows with a ``gap`` add that constant to every successor box (state units per period).
The Jacobian bound of the closed loop is the largest |d f / d x| over 20,000 random states of X per
input (central differences): an estimate, enough for a necessary condition on the nominal model.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np
from scipy.linalg import expm

from simgap.config import load_experiment
from simgap.synthesis.controller import synthesize
from simgap.synthesis.spec import Box, Spec
from simgap.systems import System, input_grid

# SCOTS growth matrix of the system file (its [bounds] growth), for the sub-models' Jacobian bounds
L4 = np.array([[0, 0, 1, 0], [0, 0, 0, 1], [0, 4.4, 0, 0.03], [0, 39.5, 0, 0.06]])

ROWS_4D = [  # (k, inputs, half-widths of X (p, theta, v, omega), eta)
    (1, 13, (0.5, 0.1, 1.0, 1.0), (0.1, 0.01, 0.1, 0.05)),
    (1, 25, (0.3, 0.1, 0.5, 1.0), (0.05, 0.005, 0.05, 0.025)),
    (5, 25, (0.3, 0.1, 0.5, 1.0), (0.005, 0.01, 0.05, 0.05)),
    (5, 49, (0.3, 0.1, 0.5, 1.0), (0.02, 0.01, 0.1, 0.05)),
    (10, 49, (0.3, 0.1, 0.5, 1.0), (0.02, 0.01, 0.1, 0.05)),
    (5, 25, (2.0, 0.1, 2.0, 1.0), (0.1, 0.01, 0.1, 0.05)),
    (1, 49, (0.5, 0.1, 0.3, 1.0), (0.02, 0.01, 0.02, 0.05)),   # about a minute of CPU
    (1, 49, (0.5, 0.1, 0.3, 1.0), (0.02, 0.01, 0.01, 0.05)),   # about 2.5 minutes of CPU
    (1, 49, (0.5, 0.2, 0.3, 1.0), (0.02, 0.01, 0.02, 0.05)),   # theta to 0.2 (beyond the file's bounds)
]
ROWS_POLE = [(1, 13, (0.1, 1.0), (0.01, 0.05)), (5, 25, (0.1, 1.0), (0.01, 0.05)),
             (5, 49, (0.1, 1.0), (0.005, 0.025))]
ROWS_CART = [(1, 13, (0.5, 1.0), (0.1, 0.1)), (1, 13, (0.5, 1.0), (0.01, 0.1))]
# inner-loop rows: (states kept, half-widths of X (p, theta, v, omega), eta, constant gap per kept state[, gains])
LOOP_GAINS = np.array([0.0, 2.034, 0.0, 2.297])  # ctrl = u + LOOP_GAINS . x: PD on the pole only
# full-state discrete LQR of the textbook model at 0.02 s, Q = diag(0.1, 10, 0.1, 1), R = 10 and R = 1:
# the cart is stabilized too (p no longer translation invariant); sum |K_i| h_i <= 2.55 on X, no clip
LQR_R10 = np.array([0.087, 3.857, 0.221, 0.760])
LQR_R1 = np.array([0.244, 5.946, 0.529, 1.305])
ROWS_LOOP = [
    ((1, 3), (0.5, 0.1, 1.0, 1.0), (0.1, 0.005, 0.1, 0.025), None),
    ((1, 2, 3), (0.5, 0.1, 1.0, 1.0), (0.1, 0.005, 0.1, 0.025), None),
    ((1, 2, 3), (0.5, 0.1, 2.0, 1.0), (0.1, 0.004, 0.1, 0.02), None),
    ((1, 2, 3), (0.5, 0.1, 2.0, 1.0), (0.1, 0.002, 0.05, 0.01), None),
    ((1, 2, 3), (0.5, 0.1, 2.0, 1.0), (0.1, 0.002, 0.05, 0.01), (0.0002, 0.0016, 0.01)),
    ((1, 2, 3), (0.5, 0.1, 2.0, 1.0), (0.1, 0.002, 0.05, 0.01), (0.0005, 0.004, 0.023)),
    ((0, 1, 2, 3), (0.5, 0.1, 1.0, 1.0), (0.1, 0.005, 0.1, 0.025), None),
    ((0, 1, 2, 3), (0.5, 0.1, 2.0, 1.0), (0.05, 0.004, 0.1, 0.02), None),   # about a minute of CPU
    ((0, 1, 2, 3), (1.0, 0.1, 2.0, 1.0), (0.1, 0.004, 0.1, 0.02), None),    # about 2 minutes, 2.3 GB
    ((0, 1, 2, 3), (0.5, 0.1, 1.0, 1.0), (0.05, 0.004, 0.1, 0.02), None, LQR_R10),
    ((0, 1, 2, 3), (0.5, 0.1, 1.0, 1.0), (0.05, 0.004, 0.1, 0.02), None, LQR_R1),
]


def run(system: System, k: int, nu: int, half, eta) -> tuple:
    half = np.asarray(half, float)
    s = dataclasses.replace(system.with_steps(k), x_lo=-half, x_hi=half, inputs=input_grid([-3], [3], [nu]))
    t = time.process_time()
    r = synthesize(s, Spec(kind="invariance", safe=Box(s.x_lo, s.x_hi)), list(eta), gap=None)
    cells = int(np.prod(np.ceil(2 * half / np.asarray(eta) - 1e-9)))
    return r.controller.size, cells, time.process_time() - t


def inner_loop_system(cp: System, dims, half, gains=LOOP_GAINS, n_inputs: int = 5, offset: float = 0.5) -> System:
    """The cart-pole under the fixed inner loop ctrl = clip(u + gains . x, -3, 3) (held for one
    period), restricted to the states ``dims`` (the others 0: exact when p is dropped and the gains
    do not use it, as f does not depend on p), with X = [-half, half] and offsets u in [-offset, offset]."""
    dims = list(dims)
    gains = np.asarray(gains, float)
    half = np.asarray(half, float)
    U = input_grid([-offset], [offset], [n_inputs])

    def full(X, u):
        return cp.step(X, np.clip(u + X @ gains[:, None], -3.0, 3.0), cp.base_tau)

    def step(x, u, dt):
        X = np.zeros((x.shape[0], 4))
        X[:, dims] = x
        return full(X, u)[:, dims]

    rng = np.random.default_rng(0)
    xs = rng.uniform(-half, half, (20_000, 4))
    J = np.zeros((4, 4))
    for uu in U:
        ur = np.broadcast_to(uu, (xs.shape[0], 1))
        for j in range(4):
            h = np.zeros(4)
            h[j] = 1e-6
            J[:, j] = np.maximum(J[:, j], (np.abs(full(xs + h, ur) - full(xs - h, ur)) / 2e-6).max(axis=0))
    Jd = J[np.ix_(dims, dims)] + 1e-6
    return System(name="cartpole_inner_loop", state_names=tuple(cp.state_names[i] for i in dims), input_names=("u",),
                  x_lo=-half[dims], x_hi=half[dims], inputs=U, base_tau=cp.base_tau, step=step,
                  jacobian_bound=lambda u: np.broadcast_to(Jd, (np.atleast_2d(u).shape[0],) + Jd.shape))


def run_loop(cp: System, dims, half, eta, gap, gains=LOOP_GAINS) -> tuple:
    s = inner_loop_system(cp, dims, half, gains)
    e = np.asarray(eta, float)[list(dims)]
    t = time.process_time()
    inv = (0,) if 0 in dims and gains[0] == 0 else ()  # p is translation invariant unless the loop feeds it back
    r = synthesize(s, Spec(kind="invariance", safe=Box(s.x_lo, s.x_hi)), list(e), gap=gap, invariant_dims=inv)
    cells = int(np.prod(np.ceil((s.x_hi - s.x_lo) / e - 1e-9)))
    return r.controller.size, cells, time.process_time() - t


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", choices=["4d", "pole", "cart", "loop"])
    a = ap.parse_args(argv)
    cp = load_experiment("cartpole", profile=None).system
    tau = cp.base_tau

    def pole_step(x, u, dt):  # (theta, omega) through the 4-state model with p = v = 0
        X = np.zeros((x.shape[0], 4))
        X[:, 1], X[:, 3] = x[:, 0], x[:, 1]
        return cp.step(X, u, dt)[:, [1, 3]]

    pole = System(name="cartpole_pole", state_names=("theta", "omega"), input_names=("u",), x_lo=(-1, -1),
                  x_hi=(1, 1), inputs=cp.inputs, base_tau=tau, step=pole_step,
                  jacobian_bound=lambda u: np.broadcast_to(expm(L4[np.ix_([1, 3], [1, 3])] * tau), (u.shape[0], 2, 2)))
    a_cart = 100.0 / (cp.params["M"] + cp.params["m"])
    cart = System(name="cartpole_cart", state_names=("p", "v"), input_names=("u",), x_lo=(-1, -1), x_hi=(1, 1),
                  inputs=cp.inputs, base_tau=tau,
                  step=lambda x, u, dt: np.stack([x[:, 0] + dt * x[:, 1] + 0.5 * dt * dt * a_cart * u[:, 0],
                                                  x[:, 1] + dt * a_cart * u[:, 0]], axis=1),
                  jacobian_bound=lambda u: np.broadcast_to(np.array([[1.0, tau], [0.0, 1.0]]), (u.shape[0], 2, 2)))
    print(f"{'model':6s} {'k':>3s} {'U':>3s} {'X half-widths':28s} {'eta':28s} {'winning':>9s} {'cells':>9s} {'CPU s':>6s}")
    for name, system, rows in (("4d", cp, ROWS_4D), ("pole", pole, ROWS_POLE), ("cart", cart, ROWS_CART)):
        if a.only not in (None, name):
            continue
        for k, nu, half, eta in rows:
            won, cells, cpu = run(system, k, nu, half, eta)
            print(f"{name:6s} {k:3d} {nu:3d} {str(half):28s} {str(eta):28s} {won:9,d} {cells:9,d} {cpu:6.1f}", flush=True)
    if a.only in (None, "loop"):
        print("\ninner loop ctrl = clip(u + gains . (p, theta, v, omega), -3, 3), 5 offsets u in [-0.5, 0.5]")
        print(f"{'states':16s} {'gains':28s} {'X half-widths':22s} {'eta':26s} {'gap':22s} {'winning':>9s} {'cells':>9s} "
              f"{'CPU s':>6s}")
        for dims, half, eta, gap, *gains in ROWS_LOOP:
            g = gains[0] if gains else LOOP_GAINS
            won, cells, cpu = run_loop(cp, dims, half, eta, gap, g)
            names = ",".join(cp.state_names[i] for i in dims)
            print(f"{names:16s} {str(tuple(g.tolist())):28s} {str(half):22s} {str(eta):26s} {str(gap):22s} {won:9,d} "
                  f"{cells:9,d} {cpu:6.1f}", flush=True)


if __name__ == "__main__":
    main()
