"""A full-resolution station scan's stages in one process, each head and then the merge message's work, on one
filmed capture of the simulated four-head station (own simulated station, seed 0, a 0.3 mm dent).

Run by hand (not a test):

    .venv/bin/python benchmarks/bench_station_stages.py [--capture DIR] [--repeats 3]

What the service's messages do, without the service: per head ``scan_head`` (its reconstruction and overlap
sample) and its files written as bytes; then the heads read back from those bytes and ``store_station_scan``
(merge, fuse, inspect against the nominal shaft, stream, store) on a temporary artifact store, as the
``scan_merge`` message does. Reports every repeat and the median of the repeats after the first (warm-up),
with the merge's parts (``refine_head_poses``, ``overlap_residuals``, ``thin_overlaps``). To compare two
commits, run it in a checkout of each one after the other on the same ``--capture`` (the machine's load
changes every figure; the ratio of the two is what holds). ``--capture``: the station capture directory,
filmed there first when it has none (about 80 s).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--capture", type=Path, default=None, help="station capture directory (filmed if empty)")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    import services.pipeline.station as station
    from services.formats.part import load_part
    from services.formats.ply import cloud_from_ply, cloud_to_ply
    from services.formats.station_capture import read_station_capture, thermal_path
    from services.formats.thermal import read_thermal_frame
    from services.pipeline.inspect import prepare_part_type
    from services.pipeline.scan import StageClock
    from services.pipeline.tables import TriangulationTables
    from services.simulation.hot_part import write_shaft_part
    from services.simulation.station import film_station, station_scene
    from services.storage.artifacts import ArtifactStore

    try:  # the head's overlap sample, stored beside its cloud (commits before it had none)
        from services.formats.stored_scan import overlap_sample_bytes, overlap_sample_from_bytes
    except ImportError:
        overlap_sample_bytes = overlap_sample_from_bytes = None
    parts: dict[str, float] = {}
    for name in ("refine_head_poses", "overlap_residuals", "thin_overlaps"):
        def timed(*a, _function=getattr(station, name), _name=name, **k):
            started = time.perf_counter()
            try:
                return _function(*a, **k)
            finally:
                parts[_name] = parts.get(_name, 0.0) + time.perf_counter() - started
        setattr(station, name, timed)

    scene = station_scene(scale=1.0, dent_depth_mm=0.3)
    rig = scene.rig
    with tempfile.TemporaryDirectory(prefix="bench-station-stages-") as tmp:
        tmp = Path(tmp)
        capture = args.capture or tmp / "capture"
        if not (capture / "thermal").is_dir():
            film_station(scene, seed=0).save(capture)
        heads = read_station_capture(capture, rig)
        thermal = {name: read_thermal_frame(thermal_path(capture, name))
                   for name, device in rig.devices.items() if device.kind == "thermal"}
        tables = TriangulationTables()
        part = prepare_part_type(load_part(write_shaft_part(tmp / "part")))
        store = ArtifactStore(tmp / "store")
        rows = []
        for repeat in range(args.repeats):
            seconds: dict[str, float] = {}
            files = []
            for head in heads:
                started = time.perf_counter()
                scan = station.scan_head(frames=head.frames, sequence=head.sequence, rig=rig, head=head.head,
                                         tables=tables)
                seconds[f"head {head.head}"] = time.perf_counter() - started
                files.append((scan, cloud_to_ply(scan.cloud),
                              None if overlap_sample_bytes is None else overlap_sample_bytes(scan.sample)))
            parts.clear()
            started = time.perf_counter()
            loaded = [station.HeadScan(scan.head, cloud_from_ply(ply, scan.head), scan.seconds,
                                       **({} if sample is None else {"sample": overlap_sample_from_bytes(sample)}))
                      for scan, ply, sample in files]
            clock = StageClock()
            stored = station.store_station_scan(scan_id="bench", heads=loaded, rig=rig, thermal=thermal, store=store,
                                                part=part, clock=clock)
            seconds["merge message"] = time.perf_counter() - started
            seconds |= clock.seconds | {f"merge: {name}": value for name, value in parts.items()}
            rows.append(seconds)
            print(f"repeat {repeat}: " + json.dumps({k: round(v, 3) for k, v in seconds.items()})
                  + f"; verdict {stored.outcome.inspection.report['verdict']}", flush=True)
    later = rows[1:] or rows
    print("median after the first: " + json.dumps({k: round(statistics.median(r[k] for r in later), 3)
                                                   for k in rows[0]}))


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    main()
