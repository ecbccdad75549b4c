"""`simgap gui` and `simgap plot` on stage-by-stage outputs: `simgap collect`, `certify`,
`synthesize` and `rollout` run one by one on a tiny pendulum experiment (numpy simulator, about
15 s for the module), then looked at from their folder or from --dataset/--cert/--controller/
--rollouts; files that do not belong together are refused, naming them, with nothing written."""

import shutil

import numpy as np
import pytest
from cli_helpers import REPO, simgap
from test_viz_results import TINY

from simgap.cli import main


@pytest.fixture(scope="module")
def stages(tmp_path_factory):
    """A folder with data/, cert.json, ctrl.npz, rollouts.npz and report.json made by the CLI, and
    beside it (other/) outputs that belong to something else."""
    d = tmp_path_factory.mktemp("stages")
    (d / "exp.toml").write_text(TINY)
    for args in (("collect", "exp.toml", "--out", "data", "--no-progress"),
                 ("certify", "data", "--beta", "0.05", "--out", "cert.json"),
                 ("synthesize", "--cert", "cert.json", "--spec", "exp.toml", "--out", "ctrl.npz"),
                 ("rollout", "--controller", "ctrl.npz", "--simulator", "exp.toml", "--out", "report.json",
                  "--trajectories", "rollouts.npz")):
        r = simgap(*args, cwd=d, timeout=300)
        assert r.returncode == 0, (args, r.stdout, r.stderr)
    o = d / "other"
    o.mkdir()
    from simgap.certify import CertifyOptions, certify
    from simgap.certify.certificate import load as load_cert
    from simgap.dataset import load_dataset
    from simgap.rollout import load_rollout, rollout
    from simgap.simulators import make_simulator
    from simgap.synthesis.controller import Controller, synthesize
    from simgap.synthesis.spec import Box, Spec
    from simgap.system_ref import resolve_system
    ctrl = Controller.load(d / "ctrl.npz")
    s = ctrl.system
    # a certificate of other data (another seed, coarser cover) and a controller synthesized with it
    r = simgap("collect", "exp.toml", "--out", "other/data2", "--seed", "2", "--epsilon", "0.03", "--no-progress",
               cwd=d, timeout=300)
    assert r.returncode == 0, r.stderr
    certify(load_dataset(o / "data2"), CertifyOptions(beta1=0.05, beta2=0.05)).save(o / "cert_other.json")
    synthesize(s, ctrl.spec, ctrl.grid.eta, gap=load_cert(o / "cert_other.json")).controller.save(o / "ctrl_other.npz")
    synthesize(s, ctrl.spec, ctrl.grid.eta).controller.save(o / "ctrl_nogap.npz")  # the nominal model alone
    duff = resolve_system(str(shutil.copy(REPO / "examples" / "duffing" / "duffing.toml", o / "duffing.toml")))
    synthesize(duff, Spec("invariance", safe=Box(duff.x_lo, duff.x_hi)), [0.1, 0.15]).controller.save(o / "ctrl_duffing.npz")
    nogap = Controller.load(o / "ctrl_nogap.npz")
    ro = load_rollout(d / "rollouts.npz")
    with make_simulator(ro.simulator, s) as sim:
        rollout(nogap, sim, ro.x0, n_rollouts=5, horizon=10, seed=0, mean_map_runs=0).save_npz(o / "rollouts_nogap.npz")
    return d


def _cli(capsys, *args):
    rc = main(list(map(str, args)))
    out, err = capsys.readouterr()
    return rc, out, err


def test_plot_draws_the_stage_outputs_of_a_folder(stages, capsys, tmp_path):
    """Every stage present: the rollout figures and gamma, and a line per stage (the JSON report named as
    not drawn). Before, `simgap plot` refused any folder without a run's summary.json."""
    rc, out, err = _cli(capsys, "plot", stages, "--out", tmp_path / "f", "--style", "slide", "--max-drawn", "20")
    assert rc == 0, err
    assert {p.name for p in (tmp_path / "f").iterdir()} == {f"{n}.{e}" for n in ("trajectories", "states_time",
                                                                                  "gamma_slices") for e in ("png", "pdf")
                                                            } | {".simgap-figures.json"}  # what plot wrote there
    assert "certificate: " + str(stages / "cert.json") in out and "2," in out  # winning cells, thousands
    assert "rollouts: " in out and "50 rollouts, 0 failed" in out
    assert "report.json is a rollout report (JSON)" in out


def test_plot_draws_what_is_there_and_names_what_is_absent(stages, capsys, tmp_path):
    rc, out, err = _cli(capsys, "plot", "--cert", stages / "cert.json", "--out", tmp_path / "g")
    assert rc == 0, err
    assert sorted(p.name for p in (tmp_path / "g").iterdir()) == [".simgap-figures.json", "gamma_slices.pdf", "gamma_slices.png"]
    for role in ("data set", "controller", "rollouts"):
        assert f"{role}: absent (written by `simgap" in out, role
    # a controller alone has nothing these figures draw: refused, nothing written
    rc, out, err = _cli(capsys, "plot", "--controller", stages / "ctrl.npz", "--out", tmp_path / "h")
    assert rc == 2 and "nothing to draw" in err and "certificate: absent" in err
    assert not (tmp_path / "h").exists()


BAD = [
    (("--cert", "nosuch.json"), ["--cert", "nosuch.json", "no such file"]),
    (("--dataset", "data", "--cert", "other/cert_other.json"),
     ["other/cert_other.json", "was made from the data set", "give the data it certifies"]),
    (("--cert", "cert.json", "--controller", "other/ctrl_duffing.npz"),
     ["does not belong to controller", "ctrl_duffing.npz", "'duffing'"]),
    (("--cert", "cert.json", "--controller", "other/ctrl_nogap.npz"),
     ["ctrl_nogap.npz", "synthesized on the nominal model alone", "cert.json"]),
    (("--cert", "cert.json", "--controller", "other/ctrl_other.npz"),
     ["ctrl_other.npz", "with another certificate", "cert.json"]),
    (("--controller", "ctrl.npz", "--rollouts", "other/rollouts_nogap.npz"),
     ["rollouts_nogap.npz", "of another controller", "ctrl.npz"]),
    (("--rollouts", "report.json"), ["report.json", "JSON report", "--trajectories"]),
    (("--controller", "tampered.npz"), ["tampered.npz", "modified after it was written"]),
]


@pytest.mark.parametrize("args,words", BAD, ids=["missing", "other-data", "other-system", "no-gap",
                                                  "other-cert", "other-controller", "json-report", "tampered"])
def test_stage_outputs_that_do_not_belong_together_are_refused(stages, capsys, monkeypatch, tmp_path, args, words):
    """Each refused by `simgap plot` (exit 2, the file named, no figure folder made) and `simgap gui`
    (exit 2 before any server starts)."""
    monkeypatch.chdir(stages)
    if "tampered.npz" in args:
        z = dict(np.load(stages / "ctrl.npz", allow_pickle=False))
        z["chosen"] = z["chosen"].copy()
        z["chosen"][np.flatnonzero(z["chosen"] >= 0)[0]] = 0 if z["chosen"].max() > 0 else 1
        np.savez(tmp_path / "tampered.npz", **z)
        args = tuple(str(tmp_path / "tampered.npz") if a == "tampered.npz" else a for a in args)
    for cmd in (("plot", "--out", tmp_path / "f"), ("gui", "--port", "0", "--exit-after", "0")):
        rc, out, err = _cli(capsys, cmd[0], *args, *cmd[1:])
        assert rc == 2, (cmd, out, err)
        for w in words:
            assert w in err, (cmd, w, err)
    assert not (tmp_path / "f").exists()


def test_two_certificates_in_one_folder_are_named(stages, capsys, tmp_path):
    d = tmp_path / "two"
    d.mkdir()
    for f in ("cert.json", "other/cert_other.json"):
        shutil.copy(stages / f, d)
    rc, out, err = _cli(capsys, "plot", d)
    assert rc == 2 and "holds 2 certificates (cert.json, cert_other.json)" in err and "--cert FILE" in err
    (tmp_path / "empty").mkdir()
    rc, out, err = _cli(capsys, "plot", tmp_path / "empty", "--out", tmp_path / "x")
    assert rc == 2 and "no summary.json" in err and "nor holds stage outputs" in err  # a folder of neither kind
    assert not (tmp_path / "x").exists()


def test_gui_opens_stage_outputs_without_their_data(stages, capsys):
    """The app shows the certificate, the winning domain and the rollouts of stage outputs given without
    the data set, with the controller's grid and the data's absence in its status; the command line
    names each stage."""
    from simgap_viz.app import SimgapApp
    from simgap_viz.results import load_stages
    run = load_stages(None, cert=stages / "cert.json", controller=stages / "ctrl.npz",
                      rollouts=stages / "rollouts.npz")
    app = SimgapApp(port=0, executor="serial")
    try:
        app.load_run(run)
        m = run.methods["stochastic"]
        assert app.results["collect"] is None and app.results["certify"] is m.certificate
        assert app.results["synthesize"] is m.synthesis and m.synthesis.controller.size > 1000
        assert app.results["rollout"] is m.rollouts and app.settings.eta == (0.005, 0.01)
        assert app.winning_counts is not None and app.winning_counts["winning"] > 100  # the winning layer drew it
        assert "data set: absent" in app.status.content and "ctrl.npz" in app.status.content
    finally:
        app.stop()
    rc, out, err = _cli(capsys, "gui", "--cert", stages / "cert.json", "--controller", stages / "ctrl.npz",
                        "--port", "0", "--exit-after", "0.5")
    assert rc == 0, err
    assert "simgap gui: data set: absent" in out and "simgap gui: controller: " in out and "open http" in out


@pytest.mark.browser
def test_gui_on_stage_outputs_shows_the_winning_domain_in_a_browser(stages, tmp_path):
    """Opened on a certificate, controller and rollouts (no data), the page says which stages it shows
    and which is absent, and the canvas shows the winning domain (its greens over > 5000 px), which
    the winning layer alone accounts for (the same view without it has almost none)."""
    from test_browser_app import _need_browser, _rgb
    _need_browser()
    import time

    from playwright.sync_api import sync_playwright

    from simgap_viz import screenshot as S
    from simgap_viz.app import SimgapApp
    from simgap_viz.results import load_stages

    app = SimgapApp(port=0, executor="serial")
    try:
        run = load_stages(None, cert=stages / "cert.json", controller=stages / "ctrl.npz",
                          rollouts=stages / "rollouts.npz")
        cells = run.methods["stochastic"].synthesis.controller.size
        app.load_run(run)
        with sync_playwright() as pw:
            b = pw.chromium.launch(executable_path=S.CHROMIUM, args=S.ARGS)
            try:
                page = S.open_page(b, app.url + "/?fixedDpr=1", 1280, 800)
                page.get_by_text("data set: absent", exact=False).first.wait_for(timeout=30_000)
                text = page.inner_text("body")
                S.show_tab(page, "View", settle=3.0)
                page.screenshot(path=str(tmp_path / "page.png"))
                A = _rgb(S.canvas_png(page, tmp_path / "A.png"))
                app.set_layer_visible("winning", False)
                time.sleep(2.5)
                R = _rgb(S.canvas_png(page, tmp_path / "R.png"))
            finally:
                b.close()
    finally:
        app.stop()
    assert "stage outputs" in text and "ctrl.npz" in text and f"{cells:,} winning cells" in text
    greens = lambda im: ((im[..., 1] > im[..., 0] + 40) & (im[..., 1] > im[..., 2] + 40)).sum()  # noqa: E731
    assert greens(A) > 5000, f"the winning domain is hardly visible ({greens(A)} px)"
    assert greens(R) < 0.1 * greens(A), (greens(R), greens(A))
