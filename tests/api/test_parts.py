"""Part types (recipes) over HTTP: upload a part file with its mesh, list, get, download, select per station;
bad part files and meshes are 422 problems naming the field; scans take a part type and carry the verdict."""

import json

import pytest

from services.db.models import Job, PartType, Scan
from services.simulation.hot_part import write_billet_part
from tests.api.test_api import PROBLEM, upload_rig


@pytest.fixture
def billet(tmp_path):
    """A billet part file and its STL (a coarse mesh: the API only validates it)."""
    path = write_billet_part(tmp_path / "billet", segments=48)
    return json.loads(path.read_text()), (path.parent / "billet.stl").read_bytes()


def upload_part(client, headers, part, mesh, select=False, mesh_name="billet.stl"):
    text = part if isinstance(part, (str, bytes)) else json.dumps(part)
    return client.post("/v1/part-types", headers=headers, data={"select": str(select).lower()},
                       files={"part": ("part.json", text, "application/json"),
                              "mesh": (mesh_name, mesh, "application/octet-stream")})


def test_part_type_upload_list_get_download_and_select(client, auth, billet):
    part, mesh = billet
    created = upload_part(client, auth["admin"], part, mesh)
    assert created.status_code == 201, created.text
    first = created.json()
    assert created.headers["location"] == first["links"]["self"]
    assert (first["name"], first["material"], first["selected"], first["station"]) == (
        "billet-90", "carbon-steel", False, "station1")
    assert client.get(first["links"]["part"], headers=auth["read"]).json() == part
    downloaded = client.get(first["links"]["mesh"], headers=auth["read"])
    assert downloaded.content == mesh and 'filename="billet.stl"' in downloaded.headers["content-disposition"]
    second = upload_part(client, auth["admin"], {**part, "name": "billet-90b"}, mesh, select=True).json()
    assert second["selected"]
    selected = client.post(f"/v1/part-types/{first['part_type_id']}/select", headers=auth["admin"])
    assert selected.status_code == 200 and selected.json()["selected"]
    listed = {p["part_type_id"]: p["selected"] for p in client.get("/v1/part-types", headers=auth["read"]).json()}
    assert listed == {first["part_type_id"]: True, second["part_type_id"]: False}
    assert client.get(f"/v1/part-types/{second['part_type_id']}", headers=auth["read"]).json()["name"] == "billet-90b"
    assert client.get("/v1/part-types/nope", headers=auth["read"]).status_code == 404
    assert upload_part(client, auth["operate"], part, mesh).status_code == 403
    assert client.post(f"/v1/part-types/{first['part_type_id']}/select", headers=auth["operate"]).status_code == 403


@pytest.mark.parametrize("case, expected", [
    ("not json", "part (part.json)"),
    ("unknown material", "material"),
    ("non-monotonic table", "temperatures must increase"),
    ("feature refers to nothing", "face_z"),
    ("feature misses the mesh", "body_diameter"),
    ("mesh does not load", "mesh (billet.stl)"),
    ("empty mesh", "mesh (billet.stl)"),
    ("mesh of another format", "mesh: 'billet.ply' is a .ply file"),
])
def test_bad_part_files_and_meshes_are_problems_naming_the_field(client, auth, runtime, billet, case, expected):
    part, mesh = billet
    mesh_name = "billet.stl"
    if case == "not json":
        part = '{"version": 1, "name": '
    elif case == "unknown material":
        part = {**part, "material": "unobtainium"}
    elif case == "non-monotonic table":
        part = {**part, "material": {"elongation": [[20, 0.0], [800, 0.01], [600, 0.012]]}}
    elif case == "feature refers to nothing":
        part = {**part, "features": part["features"] + [
            {"name": "length", "type": "distance", "between": ["body_diameter", "face_z"], "nominal": 200.0,
             "tolerance": [-0.5, 0.5]}]}
    elif case == "feature misses the mesh":
        part = {**part, "features": [{**part["features"][0], "region": {"min": [500, 500, 500],
                                                                        "max": [600, 600, 600]}}]}
    elif case == "mesh does not load":
        mesh = b"solid nothing\nthis is not an STL file at all\n" * 10
    elif case == "empty mesh":
        mesh = b""
    else:
        mesh_name = "billet.ply"
    response = upload_part(client, auth["admin"], part, mesh, select=True, mesh_name=mesh_name)
    assert response.status_code == 422, response.text
    assert response.headers["content-type"] == PROBLEM
    assert expected in response.json()["detail"], response.json()["detail"]
    with runtime.sessions() as session:
        assert session.query(PartType).count() == 0  # nothing stored


def test_a_scan_takes_the_named_or_the_selected_part_type(client, auth, runtime, billet):
    part, mesh = billet
    upload_rig(client, auth["admin"])
    plain = client.post("/v1/scans", headers=auth["operate"]).json()
    named = upload_part(client, auth["admin"], part, mesh).json()["part_type_id"]
    selected = upload_part(client, auth["admin"], {**part, "name": "other"}, mesh, select=True).json()["part_type_id"]
    by_name = client.post("/v1/scans", headers=auth["operate"], json={"part_type_id": named}).json()
    by_default = client.post("/v1/scans", headers=auth["operate"], json={"part_id": "p-1"}).json()
    with runtime.sessions() as session:
        def params(accepted):
            return session.get(Job, accepted["job_id"]).params["part_type_id"]

        assert (params(plain), params(by_name), params(by_default)) == (None, named, selected)
    scan = client.get(f"/v1/scans/{by_name['scan_id']}", headers=auth["read"]).json()
    assert scan["part_type_id"] == named and scan["links"]["part_type"] == f"/v1/part-types/{named}"
    assert scan["verdict"] is None and scan["features"] is None  # not run yet
    assert client.get(f"/v1/scans/{plain['scan_id']}", headers=auth["read"]).json()["part_type_id"] is None


def test_an_unknown_part_type_on_a_scan_is_a_problem_and_starts_nothing(client, auth, runtime):
    upload_rig(client, auth["admin"])
    response = client.post("/v1/scans", headers=auth["operate"], json={"part_type_id": "nope"})
    assert response.status_code == 422 and response.headers["content-type"] == PROBLEM
    assert response.json()["detail"].startswith("part_type_id: there is no part type 'nope'")
    with runtime.sessions() as session:
        assert session.query(Scan).count() == 0 and session.query(Job).count() == 0


def test_the_verdict_features_and_report_of_an_inspected_scan_are_served(client, auth, runtime, billet):
    part, mesh = billet
    upload_rig(client, auth["admin"])
    upload_part(client, auth["admin"], part, mesh, select=True)
    accepted = client.post("/v1/scans", headers=auth["operate"]).json()
    features = [{"name": "body_diameter", "type": "cylinder", "measure": "diameter", "hot": 91.24, "cold": 90.41,
                 "nominal": 90.0, "deviation": 0.41, "tolerance": [-0.3, 0.3], "uncertainty": 0.11,
                 "verdict": "NotOK", "points": 5000}]
    report = runtime.store.put_bytes(json.dumps({"verdict": "NotOK", "features": features}).encode())
    deviation = runtime.store.put_bytes(b"ply with deviation")
    runtime.tracker.start(accepted["job_id"])
    runtime.tracker.succeed(accepted["job_id"], {"artifacts": {"report.json": report, "deviation.ply": deviation},
                                                 "verdict": "NotOK", "features": features})
    scan = client.get(f"/v1/scans/{accepted['scan_id']}", headers=auth["read"]).json()
    assert scan["verdict"] == "NotOK" and scan["features"][0]["cold"] == 90.41
    assert scan["features"][0]["points"] == 5000  # the report's other fields pass through
    served = client.get(scan["links"]["report.json"], headers=auth["read"])
    assert served.headers["content-type"] == "application/json" and served.json()["verdict"] == "NotOK"
    assert client.get(scan["links"]["deviation.ply"], headers=auth["read"]).content == b"ply with deviation"
