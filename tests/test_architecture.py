"""The import rules of docs/architecture.md."""

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCIENCE = ("services.structured_light", "services.fusion", "services.calibration", "services.registration",
           "services.simulation", "services.inspection", "services.streaming", "services.pipeline",
           "services.geometry.camera", "services.geometry.distortion")
# The one place a shell may reach into the science (docs/architecture.md): a part type is validated as the inspection
# will load it (each feature fitted to the nominal mesh) when it is uploaded, lazily, in the thread pool.
ALLOWED = {"api/routers/parts.py": {"services.inspection.inspect"}}
SHELLS = ("api", "workers", "device_gateway", "services.cli")


def _imports(path: Path) -> set[str]:
    """Every module a file imports, at the top or inside functions."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


def _modules_importing(package: str) -> dict[str, set[str]]:
    return {str(path.relative_to(ROOT)): _imports(path) for path in (ROOT / package.replace(".", "/")).rglob("*.py")}


def _within(name: str, prefixes: tuple[str, ...]) -> bool:
    return any(name == prefix or name.startswith(prefix + ".") for prefix in prefixes)


def test_importing_the_api_app_loads_no_numba_rerun_or_science():
    code = "import json, sys; import api.app; print(json.dumps(sorted(sys.modules)))"
    loaded = json.loads(subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                                       check=True, timeout=120).stdout)
    # The part file's built-in materials are tables (numpy only) that the format validates names against.
    tables = {"services.inspection", "services.inspection.materials"}
    assert not [name for name in loaded if _within(name, ("numba", "rerun", "matplotlib", "workers") + SCIENCE)
                and name not in tables]


@pytest.mark.parametrize("package, forbidden", [
    ("api", ("workers", "services.cli", "services.pipeline") + SCIENCE),
    ("workers", ("api", "services.cli", "services.db")),
    ("services/cli", ("workers.actors", "workers.middleware")),
    ("device_gateway", ("api", "workers", "services.pipeline", "services.cli")),
    *((science.replace(".", "/"), SHELLS + ("services.pipeline",)) for science in SCIENCE[:7]),
    ("services/formats", SHELLS + ("services.pipeline",)),
    ("services/geometry", SHELLS + ("services.pipeline",)),
    ("services/db", SHELLS + SCIENCE),
    ("services/jobs", SHELLS + SCIENCE),
    ("services/opcua", ("api", "workers", "services.pipeline", "services.cli") + SCIENCE),
])
def test_layers_import_only_what_they_may(package, forbidden):
    offending = {path: sorted(name for name in names - ALLOWED.get(path, set()) if _within(name, forbidden))
                 for path, names in _modules_importing(package).items()}
    assert {path: names for path, names in offending.items() if names} == {}


# What a session does to rows: a router or an actor calls none of these itself, services/db does.
_ROW_METHODS = {"add", "add_all", "delete", "execute", "scalar", "scalars", "get", "flush", "merge", "query",
                "begin", "refresh"}


def _row_access(path: Path) -> list[str]:
    """What in a file reads or writes rows itself: an SQLAlchemy import, a model constructed from
    ``services.db.models`` (a row), a session's query or write (``session.get``, ``sessions.begin``...)."""
    tree = ast.parse(path.read_text())
    models = {alias.asname or alias.name for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)
              and node.module == "services.db.models" for alias in node.names}
    found = [f"imports {name}" for name in sorted(_imports(path)) if _within(name, ("sqlalchemy",))]
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        function = node.func
        if isinstance(function, ast.Name) and function.id in models and function.id[:1].isupper():
            found.append(f"line {node.lineno}: constructs a {function.id} row")
        elif isinstance(function, ast.Attribute) and function.attr in _ROW_METHODS \
                and isinstance(function.value, (ast.Name, ast.Attribute)) \
                and ast.unparse(function.value).split(".")[-1] in ("session", "sessions"):
            found.append(f"line {node.lineno}: {ast.unparse(function)}")
        elif isinstance(function, ast.Attribute) and function.attr == "sessions":
            found.append(f"line {node.lineno}: opens a session ({ast.unparse(function)})")
    return found


def test_no_router_or_actor_queries_or_writes_rows_itself():
    """Routers and actors only translate (docs/architecture.md): the rows are read and written through
    services/db, by services/jobs (starting a job) and the pipeline's job use cases (running one). A router
    may commit its request's session (the request is the transaction) and name models as types."""
    files = [*sorted((ROOT / "api" / "routers").glob("*.py")), *sorted((ROOT / "workers").glob("*.py"))]
    assert len(files) > 10
    offending = {str(path.relative_to(ROOT)): found for path in files if (found := _row_access(path))}
    assert offending == {}


def test_the_row_check_finds_a_query_a_write_and_a_row(tmp_path):
    router = tmp_path / "router.py"
    router.write_text("from sqlalchemy import select\nfrom services.db.models import Job, Scan\n"
                      "def list_jobs(session):\n    return session.scalars(select(Job))\n"
                      "def add(runtime):\n    with runtime.sessions.begin() as session:\n"
                      "        session.add(Scan(id='x'))\n")
    assert sorted(_row_access(router)) == ["imports sqlalchemy", "line 4: session.scalars",
                                           "line 6: runtime.sessions.begin", "line 7: constructs a Scan row",
                                           "line 7: session.add"]


def test_the_register_command_loads_neither_numba_nor_scipy_nor_pydantic(tmp_path):
    """Their imports alone (about 0.5 s each with numba's first call; pydantic's 0.07 s) cost a fair part of
    SimpleITK's whole registration; so would Open3D's, and tifffile's (0.1 s) for PNG images. The command's imports
    are numpy's and OpenCV's, about 0.2 s of its process (docs/registration.md, Time)."""
    import cv2
    import numpy as np

    rng = np.random.default_rng(0)
    scene = (255 * cv2.GaussianBlur(rng.random((160, 200)), (0, 0), 3.0)).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "visible.png"), cv2.equalizeHist(scene))
    cv2.imwrite(str(tmp_path / "infrared.png"), 255 - cv2.equalizeHist(scene))
    code = ("import json, sys\nfrom services.cli.main import main\n"
            f"status = main(['register', '--fixed', {str(tmp_path / 'visible.png')!r}, "
            f"'--moving', {str(tmp_path / 'infrared.png')!r}, '--out', {str(tmp_path / 'reg.json')!r}])\n"
            "print(json.dumps([status, sorted(sys.modules)]))")
    status, loaded = json.loads(subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                                               check=True, timeout=120).stdout.splitlines()[-1])
    assert status == 0 and (tmp_path / "reg.json").is_file()
    assert "services.registration.register" in loaded
    assert not [name for name in loaded if _within(name, ("numba", "scipy", "pydantic", "open3d", "tifffile"))]


_FIELD_WITHOUT_HEAVY_IMPORTS = """
import json, sys
import numpy as np
import services.cli.fusion, services.fusion.colormap, services.fusion.field, services.fusion.fuse
import services.fusion.visibility
from services.fusion.colormap import colormap_lut
from services.fusion.field import temperature_field
from services.fusion.fuse import ThermalView
from services.geometry.camera_model import CameraModel

imported = sorted(sys.modules)
x, y = (value.ravel() for value in np.meshgrid(np.linspace(-300, 300, 120), np.linspace(-240, 240, 100)))
cloud = {"x": x, "y": y, "z": np.full_like(x, 600.0), "nx": np.zeros_like(x), "ny": np.zeros_like(x),
         "nz": -np.ones_like(x)}
cloud["nx"][::50] = np.nan  # a few unknown normals, estimated from their neighbours
thermal = CameraModel(kind="thermal", width=80, height=64, K=np.array([[60.0, 0, 39.5], [0, 60.0, 31.5], [0, 0, 1]]))
field = temperature_field(cloud, [ThermalView(thermal, np.full((64, 80), 300.0))], np.zeros(3))
colormap_lut("coolwarm")
print(json.dumps([imported, sorted(sys.modules), int(np.isfinite(field["temperature"]).sum())]))
"""


def test_the_fusion_modules_load_neither_numba_nor_scipy_nor_matplotlib():
    """Their imports and numba's loading of its cached kernels cost ``thermofield field`` and the scan worker
    about 0.5 s; fusing a cloud with a few unknown normals and the inspection's cool-warm map need none."""
    imported, loaded, seen = json.loads(subprocess.run(
        [sys.executable, "-c", _FIELD_WITHOUT_HEAVY_IMPORTS], cwd=ROOT, capture_output=True, text=True, check=True,
        timeout=120).stdout.splitlines()[-1])
    assert seen > 7000  # of 12 000: the plane's rim, whose thermal footprint holds empty space, stays NaN
    assert not [name for name in imported if _within(name, ("numba", "scipy", "matplotlib"))]
    assert not [name for name in loaded if _within(name, ("numba", "scipy", "matplotlib"))]


def test_reconstructing_a_gray_and_phase_capture_loads_neither_numba_nor_scipy(tmp_path):
    """numba's import and the loading of its cached kernels alone (about 0.5 s) cost more than a plain numpy
    decoder's whole run of ``thermofield reconstruct``; scipy's import is most of a second."""
    import pickle

    import numpy as np

    from services.simulation.presets import forging_rig, forging_scene
    from services.simulation.render import CameraEffects, render_frames, render_view
    from services.structured_light.patterns import generate_sequence

    def scaled(device, width, height):
        K = device.K.copy()
        K[:2] *= width / device.width
        K[0, 2], K[1, 2] = (width - 1) / 2, (height - 1) / 2
        return device.replace(width=width, height=height, K=K.tolist())

    rig = forging_rig()
    camera, projector = scaled(rig.devices["camera"], 160, 100), scaled(rig.devices["projector"], 320, 200)
    sequence, patterns = generate_sequence(projector.width, projector.height)
    frames = render_frames(render_view(forging_scene(), camera, projector, supersample=1), patterns,
                           np.random.default_rng(0), CameraEffects(noise_sigma=1.0, blur_sigma=0.7))
    (tmp_path / "capture.pickle").write_bytes(pickle.dumps((frames, sequence, camera, projector)))
    capture = str(tmp_path / "capture.pickle")
    code = ("import json, pickle, sys\nimport services.structured_light.reconstruct as reconstruct\n"
            f"frames, sequence, camera, projector = pickle.loads(open({capture!r}, 'rb').read())\n"
            "cloud = reconstruct.reconstruct_points(frames, sequence, camera, projector)\n"
            "print(json.dumps([len(cloud['x']), sorted(sys.modules)]))")
    points, loaded = json.loads(subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                                               check=True, timeout=120).stdout.splitlines()[-1])
    assert points > 1000
    assert "services.structured_light.decode" in loaded and "services.structured_light.outline" in loaded
    assert not [name for name in loaded if _within(name, ("numba", "scipy"))]
