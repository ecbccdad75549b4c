"""The help pages read as plain text: no reStructuredText markup, examples on their own lines,
built-in names from the registries, one output-folder convention, errors that name what exists."""

import subprocess
import sys

import pytest


def _pages():
    from simgap.cli import build_parser
    p = build_parser()
    out = {"simgap": p.format_help()}
    stack = [("simgap", p)]
    while stack:
        name, parser = stack.pop()
        for action in parser._actions:
            for sub, child in (getattr(action, "choices", None) or {}).items() if hasattr(action, "_name_parser_map") \
                    else ():
                out[f"{name} {sub}"] = child.format_help()
                stack.append((f"{name} {sub}", child))
    return out


def test_help_pages_are_plain_text():
    pages = _pages()
    assert {"simgap certify", "simgap refine", "simgap data", "simgap key", "simgap collect"} <= set(pages)
    for name, text in pages.items():
        assert "``" not in text and "::" not in text and ":func:" not in text and ":mod:" not in text, name


def test_key_examples_on_their_own_lines():
    text = _pages()["simgap key"]
    lines = [ln.strip() for ln in text.splitlines()]
    assert any(ln.startswith("simgap key new --out ~/.simgap/key") for ln in lines)
    assert any(ln.startswith("SIMGAP_SIGNING_KEY=~/.simgap/key simgap certify") for ln in lines)


def test_builtin_lists_come_from_the_registries():
    from simgap.config import builtin_experiments
    from simgap.systems import BUILTIN
    pages = _pages()
    assert "cartpole" in builtin_experiments()
    collect = " ".join(pages["simgap collect"].split())
    assert f"({', '.join(builtin_experiments())})" in collect
    assert "results/<experiment>-<profile>/data" in collect and "runs/" not in collect  # where `run` collects
    synth = " ".join(pages["simgap synthesize"].split())
    assert ", ".join(sorted(BUILTIN)) in synth


def test_collect_and_run_share_the_data_folder():
    from simgap.config import load_experiment
    e = load_experiment("pendulum", "small")
    assert e.store_dir().as_posix() == "results/pendulum-small/data"


@pytest.mark.parametrize("spec", ["pendulm"])
def test_unknown_spec_names_the_experiments(spec, tmp_path):
    r = subprocess.run([sys.executable, "-m", "simgap", "synthesize", "--spec", spec, "--no-gap", "--out",
                        str(tmp_path / "c.npz")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "built-in experiments: cartpole, double_pendulum, kuka, pendulum, reacher, turtlebot" in r.stderr, r.stderr


def test_top_level_summaries_match_the_subcommands():
    """``simgap --help`` lists the subcommands from SUMMARIES without importing them: each line
    equals the help its module registers, and every subcommand is listed."""
    import argparse

    from simgap.cli import SUMMARIES, build_parser, plain
    full = build_parser()
    sub = next(a for a in full._actions if isinstance(a, argparse._SubParsersAction))
    registered = {a.dest: a.help for a in sub._choices_actions}
    assert set(registered) <= set(SUMMARIES)
    for name, text in registered.items():
        assert plain(SUMMARIES[name]) == text, name
    lazy = build_parser(None)
    lsub = next(a for a in lazy._actions if isinstance(a, argparse._SubParsersAction))
    assert {a.dest: a.help for a in lsub._choices_actions} == registered
    assert lazy.format_help() == full.format_help()


def test_help_and_a_command_import_only_what_they_use():
    code = ("import sys\nfrom simgap.cli import main\ntry:\n    main({argv!r})\nexcept SystemExit:\n    pass\n"
            "print(sorted(m for m in ('numpy', 'pydantic', 'simgap.cli.collect', 'simgap.cli.synthesize', "
            "'simgap_viz') if m in sys.modules), file=sys.stderr)\n")
    def loaded(argv):
        p = subprocess.run([sys.executable, "-c", code.format(argv=argv)], capture_output=True, text=True)
        return p.stderr.strip().splitlines()[-1]
    assert loaded(["--help"]) == "[]"
    assert loaded(["synthesize", "--help"]) == "['numpy', 'simgap.cli.synthesize']"
