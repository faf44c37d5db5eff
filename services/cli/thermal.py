"""``thermofield thermal convert``: any radiometric thermal file to a float32 TIFF of object temperatures (°C).

The measurement-condition options are shared with ``fuse`` and ``field`` (:func:`add_condition_arguments`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from services.errors import InputError


def add_condition_arguments(parser: argparse.ArgumentParser) -> None:
    """The user's measurement conditions, replacing those of the files (R-JPEG) or sidecars."""
    parser.add_argument("--emissivity", type=float, metavar="E",
                        help="object emissivity in (0, 1]; oxidised steel at 1000 C is about 0.8..0.9 (default: the "
                             "file's or sidecar's, else 1)")
    parser.add_argument("--reflected-c", type=float, metavar="T",
                        help="reflected apparent temperature of the surroundings, degrees C (default: the file's or "
                             "sidecar's, else 20)")
    parser.add_argument("--atmosphere-c", type=float, metavar="T",
                        help="air temperature, degrees C (default: the file's, else the reflected temperature)")
    parser.add_argument("--humidity", type=float, metavar="H",
                        help="relative humidity of the air as a fraction in [0, 1], 0.5 = 50 %% (default: the "
                             "file's, else 0.5)")
    parser.add_argument("--distance-m", type=float, metavar="D",
                        help="object distance in metres, for the air's transmission (default: the file's, else 0: "
                             "no atmosphere)")


def condition_overrides(args: argparse.Namespace):
    """The :class:`RadiometricOverrides` the options give."""
    from services.formats.thermal import RadiometricOverrides

    try:
        return RadiometricOverrides(emissivity=args.emissivity, reflected_c=args.reflected_c,
                                    atmosphere_c=args.atmosphere_c, relative_humidity=args.humidity,
                                    distance_m=args.distance_m)
    except InputError as error:
        option = {"emissivity": "--emissivity", "reflected temperature": "--reflected-c",
                  "atmospheric temperature": "--atmosphere-c", "relative humidity": "--humidity",
                  "object distance": "--distance-m"}
        message = str(error)
        name = next((name for name in option if message.startswith(name)), None)
        raise InputError(message if name is None else option[name] + message[len(name):]) from None


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("thermal")
    actions = parser.add_subparsers(dest="thermal_command", required=True, metavar="ACTION")
    convert = actions.add_parser(
        "convert",
        help="a radiometric thermal file to a float32 TIFF of object temperatures in degrees C",
        description="Read a thermal file (FLIR radiometric JPEG; float TIFF/.npy in degrees C; 16-bit PNG/TIFF in "
                    "centikelvin, or counts with a sidecar JSON stating a linear scale and offset or Planck "
                    "constants) and write object temperatures in degrees C as a float32 TIFF (NaN: no "
                    "temperature). The conditions default to the file's own (docs/thermal-formats.md).",
    )
    convert.add_argument("input", type=Path, metavar="IN", help="thermal file (.jpg/.jpeg R-JPEG, .tif, .tiff, "
                                                                 ".png, .npy)")
    convert.add_argument("output", type=Path, metavar="OUT.tiff", help="float32 TIFF to write, degrees C")
    add_condition_arguments(convert)
    convert.set_defaults(handler=_run_convert)


def _run_convert(args: argparse.Namespace) -> int:
    import numpy as np

    from services.formats.thermal import read_thermal_frame, write_thermal_frame

    if args.output.suffix.lower() not in (".tif", ".tiff"):
        raise InputError(f"{args.output}: the output is a float32 TIFF; name it .tif or .tiff")
    temperature = read_thermal_frame(args.input, overrides=condition_overrides(args))
    write_thermal_frame(args.output, temperature)
    finite = temperature[np.isfinite(temperature)]
    height, width = temperature.shape
    print(f"{args.output}: {width}x{height} degrees C, min {finite.min():.2f}, median {np.median(finite):.2f}, "
          f"max {finite.max():.2f}" + (f"; {temperature.size - finite.size} pixels without a temperature"
                                       if finite.size < temperature.size else ""))
    return 0
