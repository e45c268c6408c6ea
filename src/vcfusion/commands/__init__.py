"""The `vcfusion` command."""

from __future__ import annotations

import argparse
import os
import select
import signal
import sys
from pathlib import Path

from vcfusion import interrupts
from vcfusion.errors import InputError


def package_version() -> str:
    """The installed distribution's version (importlib.metadata); run from a source tree that is not
    installed, the package's own __version__, said so."""
    from importlib import metadata

    try:
        return metadata.version("vcfusion")
    except metadata.PackageNotFoundError:
        from vcfusion import __version__

        return f"{__version__} (not installed: run from a source tree)"


def build_parser() -> argparse.ArgumentParser:
    from vcfusion.commands import (bench, control, detection, drive, explain, lane_changes, metrics, prediction,
                                   simulation, study, traffic, transfer)

    parser = argparse.ArgumentParser(prog="vcfusion", description=__doc__)
    parser.add_argument("--version", action="version", version=f"%(prog)s {package_version()}")
    parser.add_argument("--device", dest="command_device", choices=("auto", "cpu", "cuda"),
                        help="where the camera renders and the detector runs: auto (the GPU when present: EGL and "
                             "CUDA), cpu (OSMesa, CPU) or cuda; default: the scenario's fusion.device, else auto")
    sub = parser.add_subparsers(dest="command", required=True)
    simulation.add_parsers(sub)  # run, scenarios, batch, build-net, render, demo
    traffic.add_parsers(sub)  # gen-net
    study.add_parsers(sub)  # study identification | guidance | hitl
    explain.add_parsers(sub)  # explain-highlights, guidance-matrix
    drive.add_parsers(sub)
    bench.add_parsers(sub)  # bench, bench-render
    prediction.add_parsers(sub)  # dataset, train, evaluate, bench-predict
    lane_changes.add_parsers(sub)  # compare-lane-changes, calibrate-lane-changes
    transfer.add_parsers(sub)  # real-split, retune, set-decision, ensemble-models, sim-to-real
    detection.add_parsers(sub)  # train-detector, eval-detector, render-scenes, resize-dataset, coco-check, export-onnx
    metrics.add_parsers(sub)  # metrics, report
    control.add_parsers(sub)  # export-commonroad
    return parser


def _stdout_reader_gone() -> bool:
    """Whether standard output is a pipe whose reader has closed it (`vcfusion ... | head`): its
    write end then polls as an error. A broken pipe anywhere else (a worker's) is a failure."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # not a file (a test's capture)
        return False
    poller = select.poll()
    poller.register(fd, select.POLLOUT)
    return any(events & select.POLLERR for _, events in poller.poll(0))


def _silence_stdout() -> None:
    """Point standard output at /dev/null, so what is left to flush at exit goes nowhere."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.command_device:  # before anything imports OpenGL; worker processes inherit it (vcfusion.accel)
        os.environ["VCFUSION_DEVICE"] = args.command_device
    with interrupts.recorded():  # Ctrl-C stops the command even when numba swallowed its KeyboardInterrupt
        try:
            code = args.func(args)
            sys.stdout.flush()  # a closed pipe shows here, where it is handled, not at exit
            return code
        except SystemExit:
            raise
        except BaseException as exc:
            if isinstance(exc, BrokenPipeError) and _stdout_reader_gone():
                # the reader of our output went away: nothing more can be shown, and no traceback
                _silence_stdout()
                return 128 + signal.SIGPIPE
            if interrupts.is_interrupt(exc):  # also when numba mangled it on its way up
                # What Ctrl-C left and how to go on: the command's set_defaults(interrupted=...).
                # The workers were stopped and temporary folders removed on the way up.
                hint = getattr(args, "interrupted", None)
                terminated = interrupts.terminated()  # SIGTERM, else Ctrl-C
                print(("terminated" if terminated else "interrupted") + (f": {hint}" if hint else ""), file=sys.stderr)
                return 143 if terminated else 130
            # scenario, model, dataset, command-line values; an output that exists (our own message)
            if isinstance(exc, InputError) or (isinstance(exc, FileExistsError) and exc.filename is None):
                for line in str(exc).splitlines():  # one line per problem (a scenario file may have several)
                    print(f"error: {line}", file=sys.stderr)
                return 2
            if isinstance(exc, OSError) and exc.filename is not None:
                # a path the command could not write or read (no permission, a folder where a file
                # goes, a missing parent, a file where a folder goes): the path and the reason
                what = f" (-> {exc.filename2})" if exc.filename2 else ""
                reason = exc.strerror or str(exc)
                if isinstance(exc, FileExistsError) and Path(exc.filename).is_file():
                    reason = "is a file; expected a folder (or a path that does not exist yet)"
                print(f"error: {exc.filename}{what}: {reason}", file=sys.stderr)
                return 2
            from vcfusion.errors import JobError
            from vcfusion.traffic.session import RunError

            if isinstance(exc, (RunError, JobError)):
                print(f"error: {exc}", file=sys.stderr)
                return 1
            raise
