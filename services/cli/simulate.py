"""``thermofield simulate``: render what the rig's camera captures of a scene while the projector shows a sequence."""

from __future__ import annotations

import argparse
import math
import re
from pathlib import Path

import numpy as np

from services.errors import InputError
from services.formats.files import atomic_output, output_directory
from services.formats.images import read_frame_stack, write_image
from services.formats.files import write_text_atomically
from services.formats.rig import Rig, load_rig, save_rig
from services.formats.sequence import load_sequence, save_sequence
from services.formats.thermal import write_thermal_frame
from services.simulation.presets import forging_rig, forging_scene, paper_plane, paper_rig, paper_sphere
from services.simulation.render import CameraEffects, ProjectorEffects, render_frames, render_view
from services.simulation.scene import Scene, load_scene
from services.simulation.thermal import ThermalEffects, forging_temperatures, render_thermal

# The thermal frame ``simulate`` writes beside the capture when the rig has one thermal camera and the scene's
# temperatures are known: float32 degrees C, as `thermofield field --thermal` and `fuse` read it.
THERMAL_FILE = "thermal.tiff"

RIG_PRESETS = {"paper": paper_rig, "forging": forging_rig}
SIXTEEN_BIT_SUFFIXES = (".png", ".tif", ".tiff")
# A preset's name and its size; the size is parsed as any number, so that a bad one is named as such.
_SCENE_PRESET = re.compile(r"(paper-plane|paper-sphere):(.*)|forging")


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "simulate",
        description="Render the camera frames of a virtual rig while the projector shows the patterns of "
                    "DIR/sequence.json, and write them under the manifest's names with sequence.json, rig.json, "
                    "scene.json and the ground truth (depth.npy, points.npy, projector_pixels.npy, "
                    "lit_mask.png); when the rig has one thermal camera and the scene's temperatures are known (the forging "
                    "preset, or a scene file with 'temperature'), also thermal.tiff, what that camera reads in "
                    "degrees C; for the forging preset also part/part.json and its cold nominal mesh. See docs/simulator.md.",
    )
    parser.add_argument("--scene", required=True, metavar="SCENE",
                        help="scene JSON file, or a preset: paper-plane:DEPTH_MM, paper-sphere:RADIUS_MM, forging, "
                             "station[:DENT_MM] (the four-head station around a hot shaft, with a dent of DENT_MM "
                             "on the side away from the first head: its own rig, sequence and thermal cameras, so "
                             "--rig and --patterns are not given; see docs/station.md)")
    parser.add_argument("--rig", metavar="RIG", help="rig JSON file, or a preset: paper, forging")
    parser.add_argument("--patterns", type=Path, metavar="DIR",
                        help="directory with sequence.json and the projector pattern images")
    parser.add_argument("--scale", type=float, default=1.0,
                        help="station scene only: shrink the heads' images and focal lengths (default 1)")
    parser.add_argument("--out", required=True, type=Path, metavar="DIR", help="output directory (created if needed)")
    parser.add_argument("--camera", help="camera device name (default: the rig's only camera)")
    parser.add_argument("--projector", help="projector device name (default: the rig's only projector)")
    parser.add_argument("--noise", type=float, default=1.5, metavar="GREY",
                        help="Gaussian sensor noise sigma in grey levels (default 1.5)")
    parser.add_argument("--shot-noise", type=float, default=0.0, metavar="GAIN",
                        help="shot-noise variance per grey level (default 0)")
    parser.add_argument("--blur", type=float, default=0.5, metavar="PX",
                        help="camera defocus blur sigma in camera pixels (default 0.5)")
    parser.add_argument("--projector-blur", type=float, default=0.5, metavar="PX",
                        help="projector defocus blur sigma in projector pixels (default 0.5)")
    parser.add_argument("--gamma", type=float, default=1.0, help="camera encoding gamma (default 1)")
    parser.add_argument("--projector-gamma", type=float, default=1.0, help="projector gamma (default 1)")
    parser.add_argument("--black-level", type=float, default=0.0,
                        help="projector light for pattern value 0, as a fraction of full (default 0)")
    parser.add_argument("--exposure", type=float, default=0.8,
                        help="fraction of full scale for full light on white at normal incidence (default 0.8)")
    parser.add_argument("--bit-depth", type=int, choices=(8, 16), default=8, help="frame bit depth (default 8)")
    parser.add_argument("--supersample", type=int, default=3, help="odd sub-samples per pixel side (default 3)")
    parser.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    parser.set_defaults(handler=_run)


def _scene(value: str) -> Scene:
    preset = _SCENE_PRESET.fullmatch(value)
    if preset is None:
        return load_scene(value)
    if value == "forging":
        return forging_scene()
    what = "depth" if preset[1] == "paper-plane" else "radius"
    try:
        size = float(preset[2])
    except ValueError:
        raise InputError(f"--scene: the {what} in {value!r} is not a number (e.g. {preset[1]}:100)") from None
    if not math.isfinite(size) or size <= 0:
        raise InputError(f"--scene: the {what} in {value!r} must be a positive number of millimetres")
    return paper_plane(size) if preset[1] == "paper-plane" else paper_sphere(size)


def _rig(value: str) -> Rig:
    return RIG_PRESETS[value]() if value in RIG_PRESETS else load_rig(value)


def _effects(args: argparse.Namespace) -> tuple[CameraEffects, ProjectorEffects]:
    try:
        camera = CameraEffects(exposure=args.exposure, gamma=args.gamma, blur_sigma=args.blur,
                               noise_sigma=args.noise, shot_noise_gain=args.shot_noise, bit_depth=args.bit_depth)
        projector = ProjectorEffects(gamma=args.projector_gamma, black_level=args.black_level,
                                     blur_sigma=args.projector_blur)
    except ValueError as error:
        raise InputError(f"effect options: {error}") from None
    return camera, projector


def _write_array(path: Path, array: np.ndarray) -> None:
    with atomic_output(path) as temporary, temporary.open("wb") as stream:
        np.save(stream, array)


_STATION_PRESET = re.compile(r"station(?::(.*))?")


def _run_station(args: argparse.Namespace, dent: str | None) -> int:
    from services.simulation.station import film_station, station_scene

    given = [option for option, value in (("--rig", args.rig), ("--patterns", args.patterns)) if value is not None]
    if given:
        raise InputError(f"--scene station brings its own rig and sequence; {', '.join(given)} {'does' if len(given) == 1 else 'do'} not apply")
    try:
        depth = 0.0 if dent is None else float(dent)
    except ValueError:
        raise InputError(f"--scene: the dent depth in {args.scene!r} is not a number (e.g. station:0.3)") from None
    if not math.isfinite(depth) or depth < 0 or depth > 5:
        raise InputError(f"--scene: the dent depth in {args.scene!r} must be 0 to 5 mm")
    if not 0.1 <= args.scale <= 1.0:
        raise InputError(f"--scale must be in [0.1, 1]; got {args.scale}")
    output_directory(args.out)
    station = station_scene(scale=args.scale, dent_depth_mm=depth)
    capture = film_station(station, seed=args.seed)  # one sample per pixel, as the gateway's simulated camera
    capture.save(args.out)
    save_rig(station.rig, args.out / "rig.json")
    print(f"wrote the capture of {len(capture.heads)} heads ({', '.join(h.capture.head for h in capture.heads)}) and "
          f"{len(capture.thermal)} thermal frames to {args.out}, the station's rig to {args.out / 'rig.json'}")
    return 0


def _run(args: argparse.Namespace) -> int:
    station = _STATION_PRESET.fullmatch(args.scene)
    if station is not None:
        return _run_station(args, station[1])
    missing = [option for option, value in (("--rig", args.rig), ("--patterns", args.patterns)) if value is None]
    if missing:
        raise InputError(f"the scene {args.scene!r} needs {' and '.join(missing)}")
    if args.supersample < 1 or args.supersample % 2 == 0:
        raise InputError(f"--supersample must be a positive odd number; got {args.supersample}")
    camera_effects, projector_effects = _effects(args)
    scene = _scene(args.scene)
    rig = _rig(args.rig)
    _, camera = rig.device(args.camera, "camera")
    _, projector = rig.device(args.projector, "projector")
    sequence = load_sequence(args.patterns)
    if (sequence.projector.width, sequence.projector.height) != (projector.width, projector.height):
        raise InputError(f"{args.patterns / 'sequence.json'}: projector is {sequence.projector.width}x"
                         f"{sequence.projector.height} but the rig's projector is {projector.width}x{projector.height}")
    patterns = read_frame_stack([args.patterns / frame.file for frame in sequence.frames])
    if patterns.shape[1:] != (projector.height, projector.width):
        raise InputError(f"{args.patterns}: pattern images are {patterns.shape[2]}x{patterns.shape[1]} but the "
                         f"projector is {projector.width}x{projector.height}")
    if args.bit_depth == 16:
        for frame in sequence.frames:
            if Path(frame.file).suffix.lower() not in SIXTEEN_BIT_SUFFIXES:
                raise InputError(f"{args.patterns / 'sequence.json'}: frame {frame.file!r} cannot hold 16-bit "
                                 f"images; --bit-depth 16 needs PNG or TIFF frame names")
    if args.out.resolve() == args.patterns.resolve():
        raise InputError(f"--out {args.out}: must differ from --patterns, whose images would be overwritten")
    output_directory(args.out)

    view = render_view(scene, camera, projector, args.supersample)
    frames = render_frames(view, patterns, np.random.default_rng(args.seed), camera_effects, projector_effects)
    for frame, image in zip(sequence.frames, frames):
        write_image(args.out / frame.file, image)
    save_sequence(sequence, args.out)
    save_rig(rig, args.out / "rig.json")
    write_text_atomically(args.out / "scene.json", scene.model_dump_json(indent=2, exclude_none=True) + "\n")
    _write_array(args.out / "depth.npy", view.truth.depth)
    _write_array(args.out / "points.npy", view.truth.points)
    _write_array(args.out / "projector_pixels.npy", view.truth.projector_pixels)
    write_image(args.out / "lit_mask.png", view.truth.lit.astype(np.uint8) * 255)
    print(f"wrote {len(frames)} frames of {camera.width}x{camera.height} and the ground truth to {args.out} "
          f"({view.truth.lit.mean():.1%} of pixels lit)")
    thermal = _thermal_view(args, scene, rig)
    if thermal is not None:
        write_thermal_frame(args.out / THERMAL_FILE, thermal)
        print(f"wrote what the rig's thermal camera sees, in degrees C, to {args.out / THERMAL_FILE}")
    if args.scene == "forging":
        from services.simulation.hot_part import write_forging_part

        part_file = write_forging_part(args.out / "part")
        print(f"wrote the forging's part file and cold nominal mesh (for thermofield inspect) to {part_file}")
    return 0


def _thermal_view(args: argparse.Namespace, scene: Scene, rig: Rig) -> np.ndarray | None:
    """The rig's thermal camera's image of a scene whose temperatures are known (the forging preset, or a scene
    file with ``temperature``), or None when either is missing."""
    temperatures = scene.temperature
    if temperatures is None and args.scene == "forging":
        temperatures = forging_temperatures()
    thermal = [device for device in rig.devices.values() if device.kind == "thermal"]
    if temperatures is None or len(thermal) != 1:
        return None
    return render_thermal(scene, temperatures, thermal[0], ThermalEffects(), np.random.default_rng(args.seed))
