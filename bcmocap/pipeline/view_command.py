"""``bcmocap view DIR``: see a run in the browser, and correct its joint centres and camera mounts; or see
the output of ``bcmocap markers`` or ``bcmocap kcs``.

A local web app (viser): the estimated skeleton on a time slider with play/pause and speed, the ground
truth beside it with each joint coloured by its position error, the body cameras at their solved poses
(the frontend's registered poses on request), the scene points the solver used, the selected camera's
video frame with its measurements and reprojections, the run's pictures and metrics. Select a joint
centre or a camera mount (click it, or pick it in the panel), drag the gizmo, and save: the edited model
becomes a new version of ``RUN_DIR/model/`` and ``bcmocap run`` then redoes the initial motion, the
solve and the outputs with it. A ``bcmocap markers`` folder shows the markers coloured by their segment,
the joints, the skeleton and the segments; a ``bcmocap kcs`` folder the reconstructed joints, bones and
extra links; both on the same time slider. Open the printed address in a browser (over SSH: forward the
port, ``ssh -L 8080:localhost:8080 HOST``). Ctrl-C stops the server.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import signal
import sys
import threading
import time
from collections.abc import Callable


def add_view_command(sub: argparse._SubParsersAction) -> None:
    """Register ``bcmocap view`` on the CLI's subparsers."""
    cmd = sub.add_parser("view", help="see a run (correct joint centres and camera mounts), or markers or kcs "
                         "output, in the browser", description=__doc__.split("\n\n", 1)[1])
    cmd.add_argument("run_dir", metavar="DIR",
                     help="output folder of `bcmocap run`, `bcmocap markers` or `bcmocap kcs`")
    cmd.add_argument("--port", type=int, default=8080, help="port to listen on (default 8080)")
    cmd.add_argument("--host", default="127.0.0.1",
                     help="address to listen on (default 127.0.0.1: this machine only; 0.0.0.0: every interface)")
    cmd.add_argument("--capture", help="capture folder for ground truth and videos (default: the one in run.json; "
                     "run folders only)")
    cmd.add_argument("--read-only", action="store_true", help="do not allow saving an edited model (run folders)")
    cmd.set_defaults(run=view_command)


def view_command(args: argparse.Namespace) -> int:
    """Serve the viewer until Ctrl-C."""
    return serve(args)


def serve(args: argparse.Namespace, on_ready: Callable[[object], None] | None = None,
          stop: threading.Event | None = None) -> int:
    """Read ``args.run_dir``, start the server and serve until Ctrl-C or until ``stop`` is set;
    ``on_ready(viewer)`` runs once the first frame's scene is built (tests and the benchmark drive the viewer
    there; a run's :class:`~bcmocap.viewer.app.Viewer` sets ``viewer.ready`` when the rest is in)."""
    if not 0 <= args.port <= 65535:
        print(f"bcmocap view: --port must be in 0..65535, got {args.port}", file=sys.stderr)
        return 2
    from ..viewer.server import start_server
    from .view_input import check_run_folder
    from .view_tracks import folder_kind, load_track_folder

    start = time.perf_counter()
    tracks = None
    try:
        kind = folder_kind(args.run_dir)
        if kind == "run":
            check_run_folder(args.run_dir)  # before a server starts; the rest is read while a browser loads the page
        elif args.capture is not None:
            raise ValueError(f"--capture is for a `bcmocap run` folder; {args.run_dir} is a `bcmocap {kind}` folder")
        else:
            tracks = load_track_folder(args.run_dir, kind)  # small: read whole, before a server starts
        server = start_server(args.host, args.port)
    except ValueError as exc:
        print(f"bcmocap view: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    viewer = None
    try:
        try:
            viewer, summary = _open(args, tracks, server)
        except ValueError as exc:
            print(f"bcmocap view: {' '.join(str(exc).split())}", file=sys.stderr)
            return 2
        stop = stop or threading.Event()
        if threading.current_thread() is threading.main_thread():  # Ctrl-C and `kill` end the server cleanly
            for signum in (signal.SIGINT, signal.SIGTERM):
                signal.signal(signum, lambda signum, frame: stop.set())
        host = "localhost" if args.host in ("0.0.0.0", "::") else args.host
        print(f"bcmocap view: {viewer.data.title}: {summary}; open http://{host}:{server.get_port()} "
              f"(ready in {time.perf_counter() - start:.1f} s; Ctrl-C stops)", flush=True)
        if on_ready is not None:
            on_ready(viewer)
        while not stop.wait(0.5):
            pass
        print("bcmocap view: stopped", file=sys.stderr)
    finally:
        if viewer is not None:
            viewer.close()
        with contextlib.redirect_stdout(io.StringIO()):  # viser says "Server stopped" on stdout
            server.stop()
    return 0


def _open(args: argparse.Namespace, tracks, server):
    """The viewer of the folder on ``server`` and the line that says what it shows."""
    if tracks is not None:
        from ..viewer.tracks import TrackViewer

        summary = f"`bcmocap {tracks.kind}` output, {tracks.num_frames} frames, {tracks.counts()}"
        return TrackViewer(tracks, server), summary
    from ..viewer.app import FIRST_VIEW_WAIT_S, Viewer
    from .view_input import load_view_input

    data = load_view_input(args.run_dir, args.capture, editable=not args.read_only, defer=True)
    cameras = 0 if data.rig is None else data.rig.num_cameras
    summary = f"{data.num_frames} frames, {len(data.skeleton.names)} joints, {cameras} cameras"
    return Viewer(data, server, browser_wait_s=FIRST_VIEW_WAIT_S), summary
