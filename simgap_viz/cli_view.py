"""``simgap view RUN``: serve a run's Rerun recording to a browser (no display needed).

Starts the viewer binary that ships with rerun-sdk (``rerun_cli/rerun``) with ``--web-viewer``:
it loads the .rrd files, hosts the web viewer over HTTP and the recording over gRPC, both bound
to ``--host`` (default 127.0.0.1). The web viewer only shows the recording when its address
carries ``?url=rerun+http://HOST:GRPC/proxy``; the bare ``http://HOST:WEB`` opens rerun's
welcome page. This command prints the full address, and when it ends (Ctrl+C, SIGTERM, or
``--exit-after``) it stops the viewer's whole process group, so no port stays held.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from urllib.parse import quote

from simgap.checks import check_bindable, host
from simgap.errors import SimgapError
from simgap.results_folder import check_listed


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "view", help="serve a run's Rerun recording to a browser and print its address (no display needed)",
        description="Serve RUN/run.rrd (and RUN/perrun.rrd when present), or the given .rrd files, with rerun's "
                    "web viewer; print the address that opens the recording; stop everything on exit.")
    p.add_argument("run", nargs="+", help="a `simgap run` results folder or .rrd file(s)")
    p.add_argument("--host", type=host, default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    p.add_argument("--web-port", type=_port, default=9090, help="HTTP port of the web viewer (default 9090; 0: free)")
    p.add_argument("--grpc-port", type=_port, default=9876, help="gRPC port of the recording (default 9876; 0: free)")
    p.add_argument("--exit-after", type=float, default=None, help=argparse.SUPPRESS)
    p.set_defaults(func=run)
    return p


def _port(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"port must be an integer 0..65535, got {text!r}") from None
    if not 0 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"port must be in 0..65535, got {v}")
    return v


def recordings(paths) -> list:
    """The .rrd files to serve: RUN/run.rrd (+ RUN/perrun.rrd) for a results folder, else the files given."""
    out = []
    for p in map(Path, paths):
        if p.is_dir():
            from simgap.results_folder import unfinished
            if unfinished(p):  # no summary to check its recordings against
                raise SimgapError(unfinished(p))
            files = [f for f in (p / "run.rrd", p / "perrun.rrd") if f.is_file()]
            if not files:
                raise SimgapError(f"{str(p)!r} holds no run.rrd: record it with `simgap run` (without --no-record) "
                                  "or `simgap record`")
            if (p / "summary.json").exists():  # a run's folder: serve only the recordings this run wrote
                from .results import read_summary
                summary = read_summary(p)
                for f in files:
                    check_listed(p, summary, f.name)
            out += files
        elif not p.exists():
            raise SimgapError(f"{str(p)!r} does not exist")
        elif p.suffix != ".rrd":
            raise SimgapError(f"{str(p)!r} is not a Rerun recording (.rrd) or a results folder")
        else:
            out.append(p)
    from rerun.chunk import RrdReader
    for f in out:
        try:
            ok = bool(RrdReader(str(f)).recordings())
        except Exception as e:  # the reader raises its own error types for damaged files
            raise SimgapError(f"{str(f)!r} is not a readable Rerun recording: {e}") from None
        if not ok:
            raise SimgapError(f"{str(f)!r} holds no recording")
    return out


def viewer_binary() -> str:
    """The native viewer shipped in rerun-sdk's wheel (run directly: its Python wrapper would be a
    second process, and killing the wrapper alone leaves the viewer holding the ports)."""
    try:
        import rerun_cli
        exe = Path(rerun_cli.__file__).with_name("rerun")
        if exe.is_file():
            return str(exe)
    except ImportError:
        pass
    found = shutil.which("rerun")
    if not found:
        raise SimgapError("the Rerun viewer is not installed (it ships with the rerun-sdk package)")
    return found


def _socket(bind: str) -> socket.socket:
    return socket.socket(socket.AF_INET6 if ":" in bind else socket.AF_INET, socket.SOCK_STREAM)


def _free_port(bind: str) -> int:
    with _socket(bind) as s:
        s.bind((bind, 0))
        return s.getsockname()[1]


def _check_free(bind: str, port: int, what: str) -> None:
    with _socket(bind) as s:
        try:
            s.bind((bind, port))
        except OSError:
            raise SimgapError(f"{what} port {port} on {bind} is in use (another viewer?); choose another with "
                              f"--{what}-port, or 0 for a free one") from None


def _die_with_parent() -> None:
    """In the viewer's child process before exec (Linux): SIGTERM when `simgap view` dies, even by
    SIGKILL, so no orphaned viewer keeps the ports (elsewhere only the normal exit path stops it)."""
    try:
        import ctypes
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG = 1
    except (OSError, AttributeError):
        pass


def send_recordings(files, grpc_url: str) -> None:
    """Send each .rrd file to the viewer's gRPC server, which keeps it in memory and serves it to every
    browser that opens the address (the stream carries the file's application and recording ids)."""
    import rerun as rr
    from rerun.chunk import RrdReader

    for f in files:
        entries = RrdReader(str(f)).recordings()
        e = entries[0] if entries else None
        rec = rr.RecordingStream(e.application_id if e else "simgap", recording_id=e.recording_id if e else None)
        rr.connect_grpc(grpc_url, recording=rec)
        rec.log_file_from_path(str(f))
        rec.flush()


class WebViewer:
    """The running viewer process (its own session) and the address that shows the recording."""

    def __init__(self, files, bind: str = "127.0.0.1", web_port: int = 9090, grpc_port: int = 9876,
                 timeout: float = 60.0):
        web_port = web_port or _free_port(bind)
        grpc_port = grpc_port or _free_port(bind)
        _check_free(bind, web_port, "web")
        _check_free(bind, grpc_port, "grpc")
        shown = "127.0.0.1" if bind in ("0.0.0.0", "") else ("[::1]" if bind == "::" else bind)
        self.grpc_url = f"rerun+http://{shown}:{grpc_port}/proxy"
        self.url = f"http://{shown}:{web_port}/?url={quote(self.grpc_url, safe='')}"
        self.web_port, self.grpc_port, self.log = web_port, grpc_port, []
        env = {**os.environ, "DISPLAY": "", "WAYLAND_DISPLAY": ""}  # never a native window
        # --serve-web, not --web-viewer: the latter also opens a browser, a chromium child that the viewer
        # never reaps (a defunct process while it runs). No files on its command line: the viewer then
        # polls their channel in a busy loop (about 0.3 core while idle); they are sent over gRPC instead
        self.proc = subprocess.Popen(
            [viewer_binary(), "--serve-web", "--bind", bind, "--port", str(grpc_port),
             "--web-viewer-port", str(web_port)],
            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env,
            start_new_session=True, preexec_fn=_die_with_parent)
        ready = threading.Event()

        def drain():  # keep reading so the pipe never fills; note when the web server is up
            for line in iter(self.proc.stdout.readline, b""):
                text = line.decode(errors="replace")
                self.log.append(text)
                del self.log[:-200]
                if "Hosting a web-viewer" in text:
                    ready.set()
            ready.set()

        threading.Thread(target=drain, daemon=True).start()
        if not ready.wait(timeout) or self.proc.poll() is not None:
            self.stop()
            raise SimgapError("the Rerun web viewer did not start: " + "".join(self.log[-5:]).strip())
        try:
            send_recordings(files, f"rerun+http://{'127.0.0.1' if bind in ('0.0.0.0', '') else shown}:{grpc_port}/proxy")
        except Exception as e:  # the SDK's own error types: the viewer must not outlive the failure
            self.stop()
            raise SimgapError(f"could not send the recordings to the Rerun web viewer: {e}") from None

    def stop(self) -> None:
        """Stop the viewer and everything it started (its process group); idempotent."""
        if self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, signal.SIGTERM)
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(10)
            except ProcessLookupError:
                pass


def run(args) -> int:
    check_bindable(args.host)
    files = recordings(args.run)

    def on_term(signum, frame):  # SIGTERM ends like Ctrl+C: through the finally below
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGTERM, on_term)
    viewer = None
    try:
        viewer = WebViewer(files, args.host, args.web_port, args.grpc_port)
        print(f"simgap view: serving {', '.join(map(str, files))}", flush=True)
        print(f"simgap view: open {viewer.url} in a browser (Ctrl+C to stop)", flush=True)
        if args.host in ("0.0.0.0", "::", ""):
            print(f"simgap view: WARNING: --host {args.host} serves the recording to every machine that can reach "
                  "this one", file=sys.stderr, flush=True)
        t0 = time.monotonic()
        while (args.exit_after is None or time.monotonic() - t0 < args.exit_after) and viewer.proc.poll() is None:
            time.sleep(0.2)
        if viewer.proc.poll() is not None:
            raise SimgapError("the Rerun web viewer stopped: " + "".join(viewer.log[-5:]).strip())
    except KeyboardInterrupt:
        pass
    finally:
        if viewer is not None:
            viewer.stop()
        signal.signal(signal.SIGTERM, old)
    return 0
