"""Whole-process speed of the commands a user runs, against baselines measured in the same run.

Run by hand (not a test; the machine is shared, so the ratios measured in one run are what counts):

    .venv/bin/python benchmarks/bench_commands.py [--repeats 7] [--out docs/benchmark-commands.md]

Every timing is a fresh process (``python -m services.cli.main ...``), start to exit, as a user sees it;
the medians of ``--repeats`` runs are reported, the commands and their baselines run in turn so that a
change in the machine's load hits both alike.

- ``thermofield --help``.
- ``thermofield reconstruct`` of the forging station's 1280x800 capture (30 frames, rendered once by the
  simulator): the first run with an empty table cache, then the second and later runs (the triangulation
  table loaded from the cache), against ``benchmarks/numpy_decoder.py``, a plain numpy Gray-code +
  phase-shift decoder with pinhole triangulation run the same way.
- ``thermofield field`` of the same capture and one 320x256 thermal frame (target: at most 1.0 s).
- ``thermofield register --model similarity --metric nmi`` of a 500x300 visible/infrared pair (a real TNO
  pair, the infrared moved by a known similarity), against SimpleITK's Mattes mutual-information
  registration of the same pair in-process (``benchmarks/bench_registration.simpleitk_register``; the
  ``bench`` extra): mutual information against mutual information. The default metric's whole command
  against the same baseline is ``benchmarks/bench_registration.py --command``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

TNO = ROOT.parent / "shared" / "data" / "tno-ir-visible"
_SETTLE_S = 0.3


def child_environment(**variables: str) -> dict[str, str]:
    """This process's environment with ``variables``, for the timed processes, as a user's shell would run them.

    Without PYTHONDONTWRITEBYTECODE: a session that sets it (this machine's does) recompiles every project
    module from source on each start, 0.1 to 0.3 s of a command, which no installed command pays.
    """
    environment = {name: value for name, value in os.environ.items() if name != "PYTHONDONTWRITEBYTECODE"}
    return environment | variables


def _thermofield(*args: str) -> list[str]:
    return [sys.executable, "-m", "services.cli.main", *map(str, args)]


def _seconds(command: list[str], env: dict[str, str]) -> float:
    time.sleep(_SETTLE_S)
    start = time.perf_counter()
    result = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True)
    elapsed = time.perf_counter() - start
    if result.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed: {result.stderr[-2000:]}")
    return elapsed


def _make_capture(directory: Path) -> tuple[Path, Path, Path]:
    """The forging station's 1280x800 capture, its rig and one 320x256 thermal frame."""
    from services.formats.images import write_png
    from services.formats.rig import save_rig
    from services.formats.sequence import save_sequence
    from services.formats.thermal import write_thermal_frame
    from services.simulation.presets import forging_rig, forging_scene
    from services.simulation.render import CameraEffects, render_frames, render_view
    from services.simulation.thermal import ThermalEffects, forging_temperatures, render_thermal
    from services.structured_light.patterns import generate_sequence

    rig, scene = forging_rig(), forging_scene()
    camera, projector, thermal = rig.devices["camera"], rig.devices["projector"], rig.devices["thermal"]
    rng = np.random.default_rng(0)
    sequence, patterns = generate_sequence(projector.width, projector.height)
    frames = render_frames(render_view(scene, camera, projector, supersample=1), patterns, rng,
                           CameraEffects(noise_sigma=1.5, blur_sigma=0.7))
    capture = directory / "capture"
    capture.mkdir()
    for frame, image in zip(sequence.frames, frames):
        write_png(capture / frame.file, image)
    save_sequence(sequence, capture)
    save_rig(rig, directory / "rig.json")
    write_thermal_frame(directory / "thermal.tif",
                        render_thermal(scene, forging_temperatures(), thermal, ThermalEffects(netd=0.05), rng))
    return directory / "rig.json", capture, directory / "thermal.tif"


def _make_pair(directory: Path) -> tuple[Path, Path, np.ndarray, np.ndarray]:
    """A 500x300 crop of TNO pair 01, the infrared moved by 2 degrees, 3 % and (6, -4) px."""
    visible = cv2.imread(str(TNO / "vi" / "01.png"), cv2.IMREAD_GRAYSCALE)[100:400, 100:600]
    infrared = cv2.imread(str(TNO / "ir" / "01.png"), cv2.IMREAD_GRAYSCALE)[100:400, 100:600]
    move = cv2.getRotationMatrix2D((250, 150), 2.0, 1.03)
    move[:, 2] += (6, -4)
    infrared = cv2.warpAffine(infrared, move, (500, 300), borderMode=cv2.BORDER_REFLECT)
    cv2.imwrite(str(directory / "visible.png"), visible)
    cv2.imwrite(str(directory / "infrared.png"), infrared)
    return directory / "visible.png", directory / "infrared.png", visible, infrared


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--out", type=Path, help="also write the table as Markdown")
    parser.add_argument("--only", choices=["reconstruct"],
                        help="time only this command and its baseline (reconstruct: against the numpy decoder)")
    args = parser.parse_args()
    if args.only == "reconstruct":
        _reconstruct_only(args.repeats, args.out)
        return
    from benchmarks.bench_registration import simpleitk_register

    with tempfile.TemporaryDirectory() as scratch:
        work = Path(scratch)
        env = child_environment(PYTHONPATH=str(ROOT), XDG_CACHE_HOME=str(work / "cache"))
        rig, capture, thermal = _make_capture(work)
        visible_path, infrared_path, visible, infrared = _make_pair(work)
        reconstruct = _thermofield("reconstruct", "--rig", rig, "--captures", capture, "--out", work / "c.ply")
        baseline = [sys.executable, str(ROOT / "benchmarks" / "numpy_decoder.py"), str(rig), str(capture),
                    str(work / "b.ply")]
        field = _thermofield("field", "--rig", rig, "--captures", capture, "--thermal", thermal,
                             "--out", work / "f.ply")
        register = _thermofield("register", "--fixed", visible_path, "--moving", infrared_path,
                                "--model", "similarity", "--metric", "nmi", "--out", work / "reg.json")
        first_reconstruct = _seconds(reconstruct, env)  # empty cache: builds and keeps the table
        times: dict[str, list[float]] = {name: [] for name in
                                         ("help", "reconstruct", "numpy decoder", "field", "register", "SimpleITK")}
        for _ in range(args.repeats):
            times["help"].append(_seconds(_thermofield("--help"), env))
            times["reconstruct"].append(_seconds(reconstruct, env))
            times["numpy decoder"].append(_seconds(baseline, env))
            times["field"].append(_seconds(field, env))
            times["register"].append(_seconds(register, env))
            time.sleep(_SETTLE_S)
            start = time.perf_counter()
            simpleitk_register(visible, infrared, 1.0, gradient=False)
            times["SimpleITK"].append(time.perf_counter() - start)
    median = {name: statistics.median(values) for name, values in times.items()}
    load = os.getloadavg()
    rows = [
        ("`thermofield --help`", median["help"], "", "at most 0.3 s"),
        ("`thermofield reconstruct`, first run (builds the table)", first_reconstruct, "", ""),
        ("`thermofield reconstruct`, later runs (table from the cache)", median["reconstruct"],
         f"{median['reconstruct'] / median['numpy decoder']:.2f}x the numpy decoder", "at most 1x"),
        ("`python benchmarks/numpy_decoder.py` (baseline)", median["numpy decoder"], "", ""),
        ("`thermofield field` (capture + one thermal frame)", median["field"], "", "at most 1.0 s"),
        ("`thermofield register --model similarity --metric nmi`, 500x300", median["register"],
         f"{median['register'] / median['SimpleITK']:.2f}x SimpleITK", "at most 1x"),
        ("SimpleITK Mattes MI, in-process (baseline)", median["SimpleITK"], "", ""),
    ]
    lines = [f"Medians of {args.repeats} runs, whole processes; load average {load[0]:.1f} / {load[1]:.1f} / "
             f"{load[2]:.1f} (1/5/15 min) on {os.cpu_count()} cores while it ran.", "",
             "| what | seconds | ratio in the same run | target |", "|---|---|---|---|"]
    lines += [f"| {name} | {seconds:.3f} | {ratio} | {target} |" for name, seconds, ratio, target in rows]
    text = "\n".join(lines)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")


def _reconstruct_only(repeats: int, out: Path | None) -> None:
    """``--only reconstruct``: the later runs of ``thermofield reconstruct`` against the numpy decoder."""
    with tempfile.TemporaryDirectory() as scratch:
        work = Path(scratch)
        env = child_environment(PYTHONPATH=str(ROOT), XDG_CACHE_HOME=str(work / "cache"))
        rig, capture, _ = _make_capture(work)
        reconstruct = _thermofield("reconstruct", "--rig", rig, "--captures", capture, "--out", work / "c.ply")
        baseline = [sys.executable, str(ROOT / "benchmarks" / "numpy_decoder.py"), str(rig), str(capture),
                    str(work / "b.ply")]
        first_reconstruct = _seconds(reconstruct, env)
        times: dict[str, list[float]] = {"reconstruct": [], "numpy decoder": []}
        for _ in range(repeats):
            times["reconstruct"].append(_seconds(reconstruct, env))
            times["numpy decoder"].append(_seconds(baseline, env))
    median = {name: statistics.median(values) for name, values in times.items()}
    load = os.getloadavg()
    text = "\n".join([
        f"Medians of {repeats} runs, whole processes; load average {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f} "
        f"(1/5/15 min) on {os.cpu_count()} cores while it ran.", "",
        "| what | seconds | ratio in the same run | target |", "|---|---|---|---|",
        f"| `thermofield reconstruct`, first run (builds the table) | {first_reconstruct:.3f} |  |  |",
        f"| `thermofield reconstruct`, later runs (table from the cache) | {median['reconstruct']:.3f} | "
        f"{median['reconstruct'] / median['numpy decoder']:.2f}x the numpy decoder | at most 1x |",
        f"| `python benchmarks/numpy_decoder.py` (baseline) | {median['numpy decoder']:.3f} |  |  |"])
    print(text)
    if out:
        out.write_text(text + "\n")


if __name__ == "__main__":
    main()
