"""The table of docs/thermal-formats.md: the six real FLIR radiometric JPEGs of ../shared/data/flir-rjpeg.

For each file: the camera, the thermal size, the radiometric constants and conditions the camera stored, and
the object temperatures (min, median, max over the pixels that have one) by FLIR's model with the file's own
parameters and with an emissivity of 0.85 (oxidised steel), the rest of the file's conditions kept. Read by
services/formats/thermal.py exactly as ``thermofield thermal convert FILE OUT.tiff [--emissivity 0.85]`` does.

    .venv/bin/python experiments/flir_table.py [--data DIR]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from services.formats.flir import read_flir_jpeg
from services.formats.thermal import RadiometricOverrides, read_thermal_frame

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "flir-rjpeg"
STEEL = 0.85


def _spread(temperature: np.ndarray) -> str:
    finite = temperature[np.isfinite(temperature)]
    text = f"{finite.min():.1f} / {np.median(finite):.1f} / {finite.max():.1f}"
    missing = temperature.size - finite.size
    return text + (f" ({missing} px none)" if missing else "")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA, help="directory of R-JPEGs (default %(default)s)")
    args = parser.parse_args()
    files = sorted(args.data.glob("*.jpg"))
    print("| file | camera | size | R1 | R2 | B | F | O | e | d (m) | T refl / T atm (C) | RH | "
          "min / median / max C, file's e | min / median / max C, e = 0.85 |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for path in files:
        image = read_flir_jpeg(path.read_bytes(), str(path))
        planck, c = image.planck, image.conditions
        height, width = image.counts.shape
        own = read_thermal_frame(path)
        steel = read_thermal_frame(path, overrides=RadiometricOverrides(emissivity=STEEL))
        print(f"| `{path.name}` | {image.camera.removeprefix('FLIR Systems AB ')} | {width}x{height} | "
              f"{planck.R1:.2f} | {planck.R2:.6g} | {planck.B:.1f} | {planck.F:.2f} | {planck.O:.0f} | "
              f"{c.emissivity:.2f} | {c.distance_m:g} | {c.reflected_c:.2f} / {c.atmosphere_c:.2f} | "
              f"{c.relative_humidity:.2f} | {_spread(own)} | {_spread(steel)} |")


if __name__ == "__main__":
    main()
