"""``bcmocap calibrate VIDEO_OR_IMAGES --board … --model … --out CAMERA.yml``: a lens from a board video or images."""

from __future__ import annotations

import argparse
import sys
import time


def add_calibrate_command(sub: argparse._SubParsersAction) -> None:
    """Register ``bcmocap calibrate`` on the CLI's subparsers."""
    cmd = sub.add_parser(
        "calibrate", help="calibrate a fisheye lens from a board video or a folder of images",
        description="Detect a calibration board (OpenCV) in a video (frames spread over it, then a well-spread "
                    "subset) or in a folder of images, fit the lens model, and write CAMERA.yml (cv2.fisheye), "
                    "CAMERA.json (the exact lens and a report) and CAMERA.coverage.png (where on the sensor the "
                    "board was seen). The FOV, equidistant and thin-prism fisheye models are fitted with bcmocap's own "
                    "cameras and Levenberg-Marquardt, the OpenCV Kannala-Brandt model with cv2.fisheye.")
    cmd.add_argument("source", metavar="VIDEO_OR_IMAGES", help="a video file, an image folder, or one image")
    cmd.add_argument("--board", required=True,
                     help="chessboard:COLSxROWS:SQUARE_M (inner corners), circles:COLSxROWS:SPACING_M[:asymmetric] "
                          "or charuco:COLSxROWS:SQUARE_M:MARKER_M[:DICT] (squares; partial views are used)")
    cmd.add_argument("--model", default="fov", choices=["fov", "opencv_fisheye", "equidistant", "thin_prism_fisheye"],
                     help="lens model (default fov: the paper's; thin_prism_fisheye: Kannala-Brandt with decentering "
                          "and thin-prism terms, for a lens unit whose elements or sensor sit off the axis)")
    cmd.add_argument("--out", required=True, help="output file NAME.yml or NAME.json (all three files are written)")
    cmd.add_argument("--views", type=int, default=40, help="views kept for the fit at most (default 40)")
    cmd.add_argument("--stride", type=int, default=None,
                     help="examine every n-th video frame (default: spread over the video, at most --max-frames)")
    cmd.add_argument("--max-frames", type=int, default=300, help="video frames examined at most (default 300)")
    cmd.add_argument("--keep-outliers", action="store_true",
                     help="do not drop views that fit far worse than the others")
    cmd.set_defaults(run=run_calibrate)


def run_calibrate(args: argparse.Namespace) -> int:
    from ..compilation_cache import enable_compilation_cache
    from ..io.board import parse_board
    from .fit import calibrate
    from .report import output_paths, write_calibration
    from .views import detect_views, select_views

    if args.views < 3 or args.max_frames < 1 or (args.stride is not None and args.stride < 1):
        print("bcmocap calibrate: --views must be at least 3, --max-frames and --stride at least 1", file=sys.stderr)
        return 2
    start = time.perf_counter()
    board = parse_board(args.board)
    output_paths(args.out)  # a bad --out fails before the work
    enable_compilation_cache()

    def progress(done: int, total: int, found: int) -> None:
        if done % 25 == 0 or done == total:
            print(f"\r  examined {done}/{total}, board in {found}", end="", file=sys.stderr, flush=True)

    views = detect_views(args.source, board, stride=args.stride, max_frames=args.max_frames, progress=progress)
    print(file=sys.stderr)
    chosen = select_views(views, args.views)
    print(f"{board.describe}: found in {views.found} of {views.examined} images/frames; fitting {len(chosen)} "
          f"well-spread views with the {args.model} model", flush=True)
    result = calibrate(views.subset(chosen), args.model, reject_outliers=not args.keep_outliers)
    seconds = time.perf_counter() - start
    paths = write_calibration(args.out, result, seconds)
    names = result.param_names
    values = [f"{n} {v:.4f} ± {s:.2g}" for n, v, s in zip(names, _values(result), result.std)]
    print(f"{result.method}: RMS reprojection error {result.rms_px:.3f} px over {result.views.num_views} views "
          f"({int(result.views.seen.sum())} points), worst point {result.errors.max():.2f} px")
    print("  " + ", ".join(values))
    print("  per view (px): " + ", ".join(f"{n} {e:.2f}" for n, e in zip(result.views.names, result.view_rms_px)))
    if result.rejected:
        print(f"  left out (no board pose, or outliers): {', '.join(result.rejected)}")
    print(f"wrote {', '.join(map(str, paths))} ({seconds:.1f} s)")
    return 0


def _values(result):
    from .fit import params_of

    return params_of(result.model, result.camera)
