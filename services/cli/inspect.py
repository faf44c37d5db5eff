"""``thermofield inspect``: a temperature field and a part file to cold dimensions, deviations and a verdict."""

from __future__ import annotations

import argparse
from pathlib import Path



def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "inspect",
        description="Move every point of a temperature field to where it will be when cold, align the part "
                    "file's nominal mesh, fit its features, map the surface deviation and decide OK, NotOK "
                    "or NotDecidable (docs/inspection.md).",
    )
    parser.add_argument("--field", required=True, type=Path, help="temperature field (.ply with x, y, z, temperature)")
    parser.add_argument("--part", required=True, type=Path, help="part file (PART.json, docs/part-file.md)")
    parser.add_argument("--out", required=True, type=Path, help="the report (REPORT.json)")
    parser.add_argument("--cold-cloud", type=Path, metavar="COLD.ply",
                        help="also write the part's cold-equivalent points with deviation and temperature")
    parser.add_argument("--deviation", type=Path, metavar="DEVIATION.ply",
                        help="also write the field with a per-point 'deviation' (mm) and deviation colours")
    parser.add_argument("--picture", type=Path, metavar="DEVIATION.png", help="also draw the deviation map")
    parser.set_defaults(handler=_run)


def _run(args: argparse.Namespace) -> int:
    from services.formats.files import write_text_atomically
    from services.formats.part import load_part
    from services.formats.ply import read_cloud, write_cloud
    from services.inspection.inspect import report_json
    from services.inspection.picture import deviation_picture
    from services.pipeline.inspect import inspect_part

    part = load_part(args.part)
    field = read_cloud(args.field)
    outcome = inspect_part(field=field, part=part, source=str(args.field))
    inspection = outcome.inspection
    write_text_atomically(args.out, report_json(inspection.report))
    if args.deviation:
        write_cloud(args.deviation, outcome.deviation)
    if args.cold_cloud:
        write_cloud(args.cold_cloud, outcome.cold)
    if args.picture:
        deviation_picture(inspection.alignment.to_part(inspection.cold_points), inspection.deviation,
                          tuple(part.definition.surface_tolerance), args.picture,
                          f"{part.name}: {inspection.report['verdict']}")
    report = inspection.report
    print(f"{part.name}: {report['verdict']}")
    for feature in report["features"]:
        if feature.get("cold") is None:
            print(f"  {feature['name']}: not measured ({feature.get('error')})")
            continue
        print(f"  {feature['name']}: hot {feature['hot']:.3f}, cold {feature['cold']:.3f} (nominal "
              f"{feature['nominal']:g}, deviation {feature['deviation']:+.3f} +- {feature['uncertainty']:.3f}) "
              f"{feature['verdict']}")
    if inspection.heads:
        print("  heads: " + ", ".join(f"{head.head}: {head.part_points} of {head.points} points on the part"
                                      for head in inspection.heads))
    surface = report["surface"]
    print(f"  surface: deviation {surface['mean']:+.3f} +- {surface['std']:.3f} mm, "
          f"{100 * surface['fraction_outside']:.2f} % outside, {len(surface['defects'])} defects "
          f"{surface['verdict']}; alignment rms {report['alignment']['rms_mm']:.3f} mm")
    return 0
