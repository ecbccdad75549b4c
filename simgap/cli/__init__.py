"""The ``simgap`` command: a thin dispatcher over one module per subcommand.

Each module in ``SUBCOMMANDS`` defines ``add_parser(subparsers)`` (registering its parser and
setting ``func=run`` via ``set_defaults``) and ``run(args) -> int``. A parser may also set
``outputs`` (argument names of result files) and ``output_dirs`` (of result folders): they are
checked before the command does any work (:func:`simgap.file_guard.check_outputs`). Errors that
name a bad input (SimgapError) print ``error: ...`` and exit with status 2; no traceback.
"""

from __future__ import annotations

import argparse
import importlib
import re
import os
import sys

from ..errors import SimgapError

# subcommand module names under simgap.cli (and simgap_viz.cli for the app)
SUBCOMMANDS = ["collect", "certify", "audit", "synthesize", "rollout", "refine", "data", "run", "key", "plugins", "split", "fit"]
VIZ_SUBCOMMANDS = ["gui", "record", "view", "plot"]


#: the one-line help of every subcommand, for the top-level page: ``simgap --help`` and a command
#: build only the parser they need and import only that subcommand's module (each pulls numpy,
#: pydantic, simulators, ...). tests/test_help_pages.py checks these against the modules.
SUMMARIES = {
    "collect": "collect simulator data on an epsilon-cover (resumable)",
    "certify": "compute the stochastic simulation-gap certificate of a data set",
    "audit": "audit a certificate with fresh simulator runs",
    "synthesize": "synthesize a symbolic controller that treats the certified gap as a disturbance",
    "rollout": "closed-loop rollouts of a controller on a stochastic simulator",
    "refine": "trace the residual of a model to named effects and refine it",
    "data": "prepare transition data (e.g. from a measured trajectory)",
    "run": "run a case study end to end: collect, certify (both methods), audit, synthesize, roll out",
    "key": "make a key pair for signing certificates (needs simgap[sign])",
    "plugins": "list systems and simulator kinds (built-in and from installed plugins) with their keys",
    "split": "a system file with a subset of its states, the others fixed",
    "fit": "fit named parameters of a system file to noise-free simulator transitions",
    "gui": "interactive web app (viser): collect, certify, synthesize, roll out, refine",
    "record": "headless Rerun recording (.rrd) of a run: map, winning domain, gamma, data, rollouts",
    "view": "serve a run's Rerun recording to a browser and print its address (no display needed)",
    "plot": "paper-style figures of a finished run (PNG and PDF): rollouts, states over time, gamma, p_cert",
}
ALL = object()  # build_parser(ALL): every subcommand's full parser
#: the start method of a command's local pools (set by :func:`main`; read by simgap.executors)
POOL_START = None


def command_of(argv) -> "str | None":
    """The subcommand named in ``argv`` (the first token that is not an option: the top-level
    options take no value), or None."""
    for tok in argv:
        if not tok.startswith("-"):
            return tok
    return None


def build_parser(command=ALL) -> argparse.ArgumentParser:
    """The ``simgap`` parser: every subcommand's full parser (``ALL``), or only ``command``'s
    (the others as one-line entries, their modules not imported; None: none)."""
    from .. import __version__

    p = argparse.ArgumentParser(
        prog="simgap",
        description="Certify the gap between a nominal model and a stochastic simulator, "
                    "synthesize controllers that respect it, and refine the model.")
    p.add_argument("--version", action="version", version=f"simgap {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for name in SUBCOMMANDS + VIZ_SUBCOMMANDS:
        module = f"simgap.cli.{name}" if name in SUBCOMMANDS else f"simgap_viz.cli_{name}"
        if command is ALL or name == command:
            _register(sub, module)
        elif name in SUBCOMMANDS or _viz_installed():
            sub.add_parser(name, help=SUMMARIES[name])  # listed only; its module is not imported
    _numbers_are_values(p)
    _plain_help(p)
    return p


_ROLE = re.compile(r":(?:mod|func|class|meth|data|attr):`~?([^`]+)`")


def plain(text: str) -> str:
    """A docstring (reStructuredText) as a help page reads it: ``x`` -> x, :func:`x` -> x,
    "Examples::" -> "Examples:"."""
    text = _ROLE.sub(r"\1", text)
    text = text.replace("``", "")
    return re.sub(r"::(\s*\n)", r":\1", text)


def _plain_help(parser: argparse.ArgumentParser) -> None:
    """Every (sub)parser's description and argument help as plain text; a description with
    indented lines (examples) keeps its line breaks (RawDescriptionHelpFormatter)."""
    if parser.description:
        parser.description = plain(parser.description)
        if re.search(r"\n {2,}\S", parser.description):
            parser.formatter_class = argparse.RawDescriptionHelpFormatter
    if parser.epilog:
        parser.epilog = plain(parser.epilog)
    for action in parser._actions:
        if action.help and action.help is not argparse.SUPPRESS:
            action.help = plain(action.help)
        for child in (getattr(action, "choices", None) or {}).values() if isinstance(action, argparse._SubParsersAction) else ():
            _plain_help(child)


# argparse takes "-0.05,0.1" for an option (only "-5" and "-0.5" count as numbers): every
# number list that starts with a minus is a value (no simgap option looks like a number)
NEGATIVE_NUMBERS = re.compile(r"^-\.?\d[\d.,eE+\- ]*$")


def _numbers_are_values(parser: argparse.ArgumentParser) -> None:
    parser._negative_number_matcher = NEGATIVE_NUMBERS
    for action in parser._subparsers._group_actions if parser._subparsers else ():
        for child in getattr(action, "choices", {}).values():
            _numbers_are_values(child)


def _viz_installed() -> bool:
    import importlib.util
    return importlib.util.find_spec("simgap_viz") is not None


def _register(sub, module: str) -> None:
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as e:
        if e.name and (e.name == module or module.startswith(e.name + ".")):
            return  # subcommand not present in this installation
        raise
    mod.add_parser(sub)


RESUME = "run the same command again to resume (collected data and finished stages are kept)"


class Terminated(BaseException):
    """SIGTERM, raised in the main thread so that pools, stores and temporary files are closed on the
    way out as for Ctrl-C (killed at once, a worker pool leaves semaphores the resource tracker warns of)."""


def _on_sigterm(signum, frame):
    raise Terminated()


def _reap_forkserver() -> None:
    """Stop multiprocessing's forkserver, if this process started one, and wait for it. The pool
    workers are the forkserver's children, reaped by it; once it is waited for, their CPU time
    counts as this process's children's, so `time simgap run` reports the whole run's CPU (a
    two-worker collection on the forkserver: 0.05 CPU-seconds of children without this, 5.3 with it)."""
    forkserver = sys.modules.get("multiprocessing.forkserver")  # never started without its module
    if forkserver is None:
        return
    try:
        server = forkserver._forkserver
        if getattr(server, "_forkserver_pid", None) is not None:
            server._stop()
    except Exception:  # a private API of CPython's: never let it fail a command that succeeded
        pass


def main(argv=None) -> int:
    import signal
    global POOL_START
    POOL_START = "forkserver"  # see executors.PREFERRED_START (not imported here: 50 ms of multiprocessing)
    command = command_of(sys.argv[1:] if argv is None else argv)
    parser = build_parser(command if command in SUMMARIES else None)
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    old = None
    if argv is None and _main_thread():
        # a command answers Ctrl-C whatever its parent left it: an ignored SIGINT (SIG_IGN) and a blocked one
        # are inherited through fork and exec (a test runner's worker that had run a pool in-process handed
        # both on, and the command then ran its collection to the end through the signal)
        if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
            signal.signal(signal.SIGINT, signal.default_int_handler)
        if hasattr(signal, "pthread_sigmask"):
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    if signal.getsignal(signal.SIGTERM) == signal.SIG_DFL and _main_thread():
        old = signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        from ..file_guard import check_outputs
        check_outputs(args)
        rc = int(args.func(args) or 0)
        _reap_forkserver()
        return rc
    except SimgapError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"interrupted: {RESUME}", file=sys.stderr)
        return 130
    except Terminated:
        print(f"terminated: {RESUME}", file=sys.stderr)
        return 143
    except BrokenPipeError:
        # the reader went away (e.g. `simgap plugins | head`): stop quietly, as other Unix tools do;
        # stdout goes to devnull so that the interpreter's final flush does not raise again
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except Exception as e:
        # an interruption that landed inside a library's cleanup (numpy's savez closing its zip
        # raises ValueError over the Terminated it was handling) is still that interruption
        cause = _interruption_in(e)
        if cause is None:
            raise
        print(f"{'terminated' if cause is Terminated else 'interrupted'}: {RESUME}", file=sys.stderr)
        return 143 if cause is Terminated else 130
    finally:
        if old is not None:
            signal.signal(signal.SIGTERM, old)


def _interruption_in(e: BaseException):
    """Terminated or KeyboardInterrupt if one is in ``e``'s context chain, else None."""
    seen = set()
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        for kind in (Terminated, KeyboardInterrupt):
            if isinstance(e, kind):
                return kind
        e = e.__cause__ or e.__context__
    return None


def _main_thread() -> bool:
    import threading
    return threading.current_thread() is threading.main_thread()


if __name__ == "__main__":
    sys.exit(main())
