"""Who may do what: every operation but health needs a key of the right scope; keys are hashed, listed and
revoked by command and by API; each key is rate limited (429 + Retry-After)."""

import math
import re
import time

import pytest
from sqlalchemy import select

from services.db.models import ApiKey

PROBLEM = "application/problem+json"
OPEN_OPERATIONS = {"get_health", "get_readiness", "get_metrics"}
# The least scope of each operation; a key of a lower scope gets 403.
SCOPE_OF_METHOD = {"get": "read", "post": "operate", "delete": "admin"}
ADMIN_OPERATIONS = {"create_calibration_set", "activate_calibration_set", "start_stereo_calibration",
                    "start_station_calibration", "start_stereo_capture", "create_api_key", "list_api_keys", "revoke_api_key", "create_part_type",
                    "select_part_type"}
LOWER_SCOPES = {"read": [], "operate": ["read"], "admin": ["read", "operate"]}


def _operations(client):
    for path, methods in client.get("/openapi.json").json()["paths"].items():
        for method, operation in methods.items():
            concrete = re.sub(r"\{index\}", "0", re.sub(r"\{suffix\}", "png", re.sub(r"\{kind\}", "frames", path)))
            concrete = re.sub(r"\{artifact\}", "cloud.ply", re.sub(r"\{[^}]+\}", "x" * 32, concrete))
            yield operation["operationId"], method, concrete


@pytest.fixture
def patient_client(runtime, job_queue):
    """A client whose address may send any number of unknown keys (the scope checks send one per operation)."""
    from fastapi.testclient import TestClient

    from api.app import create_app

    runtime.settings = runtime.settings.model_copy(update={"auth_failure_rate_per_s": 0.0})
    with TestClient(create_app(runtime, job_queue), raise_server_exceptions=False) as client:
        yield client


def test_every_operation_but_health_needs_a_key_of_its_scope(patient_client, auth):
    client = patient_client
    operations = list(_operations(client))
    assert len(operations) >= 24
    for operation_id, method, path in operations:
        if operation_id in OPEN_OPERATIONS:
            assert client.request(method, path).status_code == 200, operation_id
            continue
        for headers in ({}, {"Authorization": "Bearer tf_not-a-key"}, {"Authorization": "Basic dXNlcjpwdw=="}):
            response = client.request(method, path, headers=headers)
            assert response.status_code == 401, (operation_id, headers, response.text)
            assert response.headers["content-type"] == PROBLEM and response.headers["www-authenticate"] == "Bearer"
        scope = "admin" if operation_id in ADMIN_OPERATIONS else SCOPE_OF_METHOD[method]
        for lower in LOWER_SCOPES[scope]:
            response = client.request(method, path, headers=auth[lower])
            assert response.status_code == 403, (operation_id, lower, response.text)
            assert response.headers["content-type"] == PROBLEM and f"'{scope}'" in response.json()["detail"]
        response = client.request(method, path, headers=auth[scope])
        assert response.status_code not in (401, 403), (operation_id, scope, response.text)


def test_keys_are_created_listed_and_revoked_through_the_api(client, auth, runtime):
    created = client.post("/v1/api-keys", headers=auth["admin"], json={"name": "mes", "scopes": ["operate"]})
    assert created.status_code == 201, created.text
    key = created.json()
    secret = key["secret"]
    assert secret.startswith("tf_") and key["scopes"] == ["operate"]
    mes = {"Authorization": f"Bearer {secret}"}
    assert client.get("/v1/scans", headers=mes).status_code == 200
    assert client.get("/v1/api-keys", headers=mes).status_code == 403  # operate cannot manage keys
    listed = client.get("/v1/api-keys", headers=auth["admin"]).json()
    assert {k["name"] for k in listed} == {"read", "operate", "admin", "mes"}
    assert all("secret" not in k for k in listed)
    with runtime.sessions() as session:  # stored hashed: the secret is nowhere in the row
        row = session.scalar(select(ApiKey).where(ApiKey.id == key["api_key_id"]))
        assert secret not in repr(vars(row)) and len(row.secret_sha256) == 64
    revoked = client.delete(f"/v1/api-keys/{key['api_key_id']}", headers=auth["admin"])
    assert revoked.status_code == 200 and revoked.json()["revoked_at"] is not None
    response = client.get("/v1/scans", headers=mes)  # at once, although it was cached
    assert response.status_code == 401 and response.headers["content-type"] == PROBLEM
    assert client.delete("/v1/api-keys/nope", headers=auth["admin"]).status_code == 404
    bad = client.post("/v1/api-keys", headers=auth["admin"], json={"scopes": ["root"]})
    assert bad.status_code == 422 and bad.headers["content-type"] == PROBLEM


@pytest.fixture
def limited_client(runtime, job_queue):
    from fastapi.testclient import TestClient

    from api.app import create_app

    runtime.settings = runtime.settings.model_copy(update={"rate_limit_per_s": 2.0, "rate_limit_burst": 3})
    with TestClient(create_app(runtime, job_queue), raise_server_exceptions=False) as client:
        yield client


def test_each_key_is_rate_limited_with_retry_after(limited_client, auth):
    statuses = [limited_client.get("/v1/jobs", headers=auth["read"]).status_code for _ in range(4)]
    assert statuses == [200, 200, 200, 429]
    response = limited_client.get("/v1/jobs", headers=auth["read"])
    assert response.status_code == 429 and response.headers["content-type"] == PROBLEM
    assert int(response.headers["retry-after"]) >= 1 and response.json()["type"].endswith("/rate-limited")
    assert limited_client.get("/v1/jobs", headers=auth["operate"]).status_code == 200  # another key is not held up
    assert limited_client.get("/healthz").status_code == 200


def test_a_request_checking_two_scopes_takes_one_token(limited_client, auth):
    # POST /v1/scans/{id}/jobs checks the operate scope and, through the scan it names, the read scope.
    statuses = [limited_client.post("/v1/scans/none/jobs", headers=auth["operate"], json={"kind": "reconstruct"})
                .status_code for _ in range(4)]
    assert statuses == [404, 404, 404, 429]


class _Result:
    def __init__(self, returncode, captured):
        self.returncode, self.stdout, self.stderr = returncode, captured.out, captured.err


@pytest.fixture
def apikey(tmp_path, capsys):
    from services.cli.main import main

    def run(*args):
        returncode = main(["apikey", *args, "--data-dir", str(tmp_path)])
        return _Result(returncode, capsys.readouterr())

    return run


def test_apikey_command_takes_scopes_as_users_type_them_lists_and_revokes(apikey):
    for scopes in (["read", "operate"], ["read,operate"], ["read,", "operate"], ["Read, Operate"]):
        result = apikey("create", "--scopes", *scopes, "--name", "x")
        assert result.returncode == 0, (scopes, result.stderr)
        assert "scopes read operate" in result.stderr and result.stdout.startswith("tf_")
    result = apikey("create", "--scopes", "read,root")
    assert result.returncode == 2 and "root" in result.stderr and len(result.stderr.strip().splitlines()) == 1
    first_id = re.search(r"created API key (\w+)", apikey("create", "--scopes", "admin").stderr).group(1)
    listed = apikey("list")
    assert listed.returncode == 0 and first_id in listed.stdout and "tf_" not in listed.stdout
    assert len(listed.stdout.strip().splitlines()) == 1 + 5
    assert apikey("revoke", first_id).returncode == 0
    row = next(line for line in apikey("list").stdout.splitlines() if line.startswith(first_id))
    assert re.search(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\s+\d{4}-\d\d-\d\d", row), row  # a revocation time
    missing = apikey("revoke", "nope")
    assert missing.returncode == 2 and "no API key 'nope'" in missing.stderr


def test_two_authorization_headers_are_refused_as_ambiguous(client, auth):
    for second in (auth["read"]["Authorization"], "Bearer tf_someone-else"):
        response = client.get("/v1/jobs", headers=[("Authorization", auth["admin"]["Authorization"]),
                                                   ("Authorization", second)])
        assert response.status_code == 400 and response.headers["content-type"] == PROBLEM, response.text
        assert response.json()["type"].endswith("/ambiguous-credentials") and "one Authorization" in \
            response.json()["detail"]
    assert client.get("/v1/jobs", headers=auth["admin"]).status_code == 200


def _requests(app, requests, address="10.0.0.1"):
    """Send ``(path, headers)`` requests all at once from ``address``; their responses in order."""
    import asyncio

    import httpx

    async def send():
        transport = httpx.ASGITransport(app=app, client=(address, 40000))
        async with httpx.AsyncClient(transport=transport, base_url="http://api") as client:
            return await asyncio.gather(*(client.get(path, headers=headers) for path, headers in requests))

    return asyncio.run(send())


@pytest.fixture
def app_and_queries(runtime, job_queue):
    """The app with a failure limit of 5 at once, 1 per second, and a list collecting its queries of API keys."""
    from sqlalchemy import event

    from api.app import create_app

    runtime.settings = runtime.settings.model_copy(update={"auth_failure_rate_per_s": 1.0, "auth_failure_burst": 5})
    queries = []

    def record(conn, cursor, statement, parameters, context, executemany):
        if "api_keys" in statement and statement.lstrip().upper().startswith("SELECT"):
            queries.append(statement)

    event.listen(runtime.engine, "before_cursor_execute", record)
    yield create_app(runtime, job_queue), queries
    event.remove(runtime.engine, "before_cursor_execute", record)


def test_unknown_keys_cost_one_query_each_and_their_address_is_then_held_off(app_and_queries, auth):
    app, queries = app_and_queries
    unknown = [{"Authorization": f"Bearer tf_unknown-{n % 4}"} for n in range(60)]
    started = time.monotonic()
    responses = _requests(app, [("/v1/jobs", headers) for headers in unknown])
    refilled = math.ceil(1.0 * (time.monotonic() - started))  # 1 per second refills while the 60 are served
    statuses = [response.status_code for response in responses]
    # a token bucket admits its burst (5) and what refilled meanwhile; a loaded machine serves the 60 slower
    assert set(statuses) <= {401, 429} and statuses.count(401) <= 5 + refilled < 60, (statuses, refilled)
    assert len(queries) <= 4, queries  # one query per distinct key at most, however many ask at once
    held_off = next(response for response in responses if response.status_code == 429)
    assert held_off.headers["content-type"] == PROBLEM and int(held_off.headers["retry-after"]) >= 1
    assert "client address" in held_off.json()["detail"]
    again = _requests(app, [("/v1/jobs", headers) for headers in unknown[:4]], address="10.0.0.2")
    assert [response.status_code for response in again] == [401] * 4  # another address is not held off
    assert len(queries) <= 4, queries  # and its unknown keys were cached: no query
    known = _requests(app, [("/v1/jobs", auth["read"])], address="10.0.0.3")
    assert known[0].status_code == 200
    assert _requests(app, [("/v1/jobs", auth["read"])])[0].status_code == 200  # a cached key passes even there
