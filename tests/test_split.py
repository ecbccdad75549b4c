"""simgap split: a system file's sub-system (chosen states, the others fixed) computes exactly what
the full model computes on that slice, and bad requests are refused by name, nothing written."""

import sys
import tomllib

import numpy as np
import pytest

from cli_helpers import REPO, refused, simgap

sys.path.insert(0, str(REPO))

from simgap.errors import SimgapError  # noqa: E402
from simgap.system_file import system_from_spec  # noqa: E402
from simgap.system_split import split_spec, toml_text  # noqa: E402

CARTPOLE = REPO / "assets" / "experiments" / "cartpole" / "cartpole.toml"


def full_spec():
    return tomllib.loads(CARTPOLE.read_text())


@pytest.mark.parametrize("keep,fixed", [(["theta", "omega"], {"p": 0.1, "v": -0.3}),
                                        (["p", "v"], {"theta": 0.05, "omega": 0.2}),
                                        (["omega", "p"], {"theta": -0.02, "v": 0.5})])
def test_the_part_is_the_full_model_with_the_others_held(keep, fixed):
    """The part equals the full model whose left-out states are held (derivative 0), on that slice."""
    spec = full_spec()
    held = dict(spec, dynamics={k: ("0" if k in fixed else v) for k, v in spec["dynamics"].items()})
    full = system_from_spec(held, "full, the others held")
    part = system_from_spec(tomllib.loads(toml_text(split_spec(spec, keep, fixed))), "part")
    names = full.state_names
    kept = [i for i, s in enumerate(names) if s in keep]  # the file's order, whatever --keep's
    assert list(part.state_names) == [names[i] for i in kept]
    rng = np.random.default_rng(0)
    x = full.x_lo + rng.random((200, full.n)) * (full.x_hi - full.x_lo)
    for s, v in fixed.items():
        x[:, names.index(s)] = v
    u = full.inputs[rng.integers(0, len(full.inputs), 200)]
    np.testing.assert_allclose(part.f(x[:, kept], u), full.f(x, u)[:, kept], rtol=0, atol=1e-12)
    # the growth bound's kept block bounds the part's Jacobian (the matrix is read from the file)
    assert part.jacobian_bound(u[:1]).shape == (1, len(kept), len(kept))


def test_split_command_and_the_pole_alone_wins(tmp_path):
    r = simgap("split", CARTPOLE, "--keep", "theta,omega", "--fix", "p=0,v=0", "--out", "pole.toml", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    r = simgap("synthesize", "--system", "pole.toml", "--no-gap", "--safe=-0.1,0.1,-1,1", "--eta", "0.01,0.05",
               "--out", "pole.npz", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "winning       723 of 741 safe cells" in r.stdout  # bench/cartpole_synthesis_probe.py --only pole: 723
    r = simgap("split", CARTPOLE, "--keep", "p,v", "--out", "cart.toml", cwd=tmp_path)
    assert r.returncode == 0 and "theta fixed at 0, the middle of its range" in r.stdout, r.stdout + r.stderr


@pytest.mark.parametrize("args,words", [
    (["--keep", "theta,phi", "--fix", "p=0,v=0"], ["no state 'phi'", "p, theta, v, omega"]),
    (["--keep", "theta,omega", "--fix", "p=0,v=9"], ["v = 9 is outside its range"]),
    (["--keep", "theta,omega", "--fix", "p=0,omega=0"], ["--fix names omega", "fix only the states left out"]),
    (["--keep", "theta,omega", "--fix", "p"], ["expected NAME=VALUE"]),
    (["--keep", "p,theta,v,omega"], ["keeping every state is the system itself"]),
])
def test_bad_splits_are_refused(tmp_path, args, words):
    refused(simgap("split", CARTPOLE, *args, "--out", "x.toml", cwd=tmp_path), *words)
    assert not (tmp_path / "x.toml").exists()


def test_an_experiment_file_is_named_as_such(tmp_path):
    refused(simgap("split", CARTPOLE.parent.parent / "cartpole.toml", "--keep", "theta", "--out", "x.toml",
                   cwd=tmp_path), "not a system file", "an experiment? split its system file, 'cartpole/cartpole.toml'")


def test_missing_values_need_the_names():
    with pytest.raises(SimgapError, match="give a value for every state left out"):
        split_spec(full_spec(), ["theta", "omega"], {"p": 0.0})
