"""The OPC UA server (OPC 40100-1 Machine Vision where it applies), read and subscribed to by a real asyncua
client: the vision system's state, recipes from the part types, a ResultReady event per finished scan."""

import asyncio
import socket
import time
import uuid

import pytest
from asyncua import Client, ua

from services.db.engine import make_sessions
from services.db.models import CalibrationSet, PartType, Scan
from services.db.parts import select_part_type
from services.errors import InputError
from services.events.job_states import JobStateSubscriber
from services.events.mqtt import EventPublisher
from services.events.opcua import NAMESPACE, RECIPE_REFRESH_S, OpcUaServer, result_state
from services.jobs.tracker import JobTracker


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class _Events:
    def __init__(self) -> None:
        self.received = []

    def event_notification(self, event) -> None:
        self.received.append({name: getattr(event, name) for name in (
            "ResultId", "PartId", "ResultState", "Verdict", "IsPartial", "JobId", "InternalRecipeId", "ProductId",
            "CreationTime", "Message")})


async def _wait_for(condition, timeout_s: float = 15.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition() and time.monotonic() < deadline:
        await asyncio.sleep(0.1)


def _scan_job(tracker: JobTracker, part_type_id: str | None, part_id: str) -> tuple[str, str]:
    with tracker.sessions.begin() as session:
        if session.get(CalibrationSet, "c1") is None:
            session.add(CalibrationSet(id="c1", name="rig", station="station1", source="upload"))
            session.flush()
        scan = Scan(station="station1", calibration_set_id="c1", part_id=part_id, part_type_id=part_type_id,
                    job_id="pending")
        job = tracker.create(session, "scan", {"scan_id": "pending"})
        scan.job_id = job.id
        session.add(scan)
        session.flush()
        job.params = {"scan_id": scan.id, "part_type_id": part_type_id}
        return job.id, scan.id


def test_state_recipes_and_a_result_ready_event_per_scan(engine):
    sessions = make_sessions(engine)
    tracker = JobTracker(sessions)
    with sessions.begin() as session:
        billet = PartType(name="billet-90", station="station1", material="carbon-steel", part_sha256="a" * 64,
                          mesh_sha256="b" * 64)
        session.add_all([billet, PartType(name="other station's", station="station2", material="carbon-steel",
                                          part_sha256="a" * 64, mesh_sha256="b" * 64)])
        session.flush()
        select_part_type(session, billet)
        billet_id = billet.id
    endpoint = f"opc.tcp://127.0.0.1:{_free_port()}/thermofield"

    async def client_side(server: OpcUaServer) -> None:
        async with Client(endpoint) as client:
            namespace = await client.get_namespace_index(NAMESPACE)
            vision = await client.nodes.objects.get_child(f"{namespace}:VisionSystem")

            async def read(*path: str):
                node = await vision.get_child([f"{namespace}:{name}" for name in path])
                return await node.read_value()

            assert (await read("VisionStateMachine", "CurrentState")).Text == "Operational"
            assert (await read("VisionStateMachine", "AutomaticModeStateMachine", "CurrentState")).Text == "Ready"
            recipes = await vision.get_child([f"{namespace}:RecipeManagement", f"{namespace}:Recipes"])
            await _wait_for_children(recipes, 1)
            (recipe,) = await recipes.get_children()
            assert (await recipe.read_browse_name()).Name == "billet-90"  # only this station's part types
            assert await (await recipe.get_child(f"{namespace}:InternalRecipeId")).read_value() == billet_id
            assert await (await recipe.get_child(f"{namespace}:Prepared")).read_value() is True

            event_type = await client.nodes.base_event_type.get_child(f"{namespace}:ResultReadyEventType")
            events = _Events()
            subscription = await client.create_subscription(50, events)
            await subscription.subscribe_events(vision, event_type)

            inspected, inspected_scan = _scan_job(tracker, billet_id, "billet-17")
            tracker.start(inspected, "host:1")
            deadline = time.monotonic() + 10
            while (running := await read("VisionStateMachine", "AutomaticModeStateMachine", "CurrentState")).Text \
                    == "Ready" and time.monotonic() < deadline:
                await asyncio.sleep(0.05)
            tracker.succeed(inspected, {"verdict": "NotOK", "features": [{"name": "body_diameter"}]})
            plain, plain_scan = _scan_job(tracker, None, "billet-18")
            tracker.start(plain)
            tracker.succeed(plain, {})
            failed, failed_scan = _scan_job(tracker, billet_id, "billet-19")
            tracker.start(failed)
            tracker.fail(failed, "GatewayError: lost", will_retry=False)
            await _wait_for(lambda: len(events.received) >= 3)

            assert running.Text == "SingleExecution"
            assert [(e["ResultId"], e["PartId"], e["ResultState"], e["Verdict"], e["InternalRecipeId"],
                     e["ProductId"], e["IsPartial"]) for e in events.received] == [
                (inspected_scan, "billet-17", 2, "NotOK", billet_id, "billet-90", False),
                (plain_scan, "billet-18", 0, "", "", "", False),
                (failed_scan, "billet-19", 0, "", billet_id, "billet-90", False)]
            assert [e["JobId"] for e in events.received] == [inspected, plain, failed]
            assert all(abs(time.time() - e["CreationTime"].timestamp()) < 60 for e in events.received)
            assert "failed: GatewayError: lost" in events.received[2]["Message"].Text
            assert await read("ResultManagement", "LastResult", "ResultId") == failed_scan
            assert (await read("VisionStateMachine", "AutomaticModeStateMachine", "CurrentState")).Text == "Ready"

            # a part type added later (by any API process) appears as a recipe; selecting another moves Prepared
            with sessions.begin() as session:
                shaft = PartType(name="shaft-40", station="station1", material="stainless-steel",
                                 part_sha256="c" * 64, mesh_sha256="d" * 64)
                session.add(shaft)
                session.flush()
                select_part_type(session, shaft)
            await _wait_for_children(recipes, 2)
            await asyncio.sleep(RECIPE_REFRESH_S + 0.5)
            prepared = {}
            for child in await recipes.get_children():
                prepared[(await child.read_browse_name()).Name] = await (
                    await child.get_child(f"{namespace}:Prepared")).read_value()
            assert prepared == {"billet-90": False, "shaft-40": True}

    with OpcUaServer(endpoint, sessions, "station1") as server:
        tracker.listeners.append(server.notify)
        asyncio.run(client_side(server))


async def _wait_for_children(node, count: int, timeout_s: float = 15.0) -> None:
    deadline = time.monotonic() + timeout_s
    while len(await node.get_children()) < count and time.monotonic() < deadline:
        await asyncio.sleep(0.2)


def test_result_states_are_the_result_evaluation_codes():
    assert [result_state(v) for v in ("OK", "NotOK", "NotDecidable", None)] == [1, 2, 3, 0]


def test_a_bad_endpoint_or_a_taken_port_is_a_clear_error(engine):
    sessions = make_sessions(engine)
    with pytest.raises(InputError, match="not an opc.tcp://host:port"):
        OpcUaServer("http://127.0.0.1:4840", sessions, "station1")
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        endpoint = f"opc.tcp://127.0.0.1:{busy.getsockname()[1]}/thermofield"
        with pytest.raises(InputError, match="cannot listen"):
            with OpcUaServer(endpoint, sessions, "station1"):
                pass


def test_scaled_out_the_workers_results_reach_opc_ua_over_mqtt(engine):
    """``thermofield api`` runs no jobs: a worker's tracker publishes the states on MQTT, the API's subscriber
    feeds its OPC UA server, which fires ResultReady as in the embedded mode."""
    sessions = make_sessions(engine)
    prefix = f"test-{uuid.uuid4().hex[:8]}/station1"
    worker_tracker = JobTracker(sessions, EventPublisher("127.0.0.1", 1883, prefix))
    endpoint = f"opc.tcp://127.0.0.1:{_free_port()}/thermofield"

    async def client_side(subscriber: JobStateSubscriber) -> None:
        async with Client(endpoint) as client:
            namespace = await client.get_namespace_index(NAMESPACE)
            vision = await client.nodes.objects.get_child(f"{namespace}:VisionSystem")
            event_type = await client.nodes.base_event_type.get_child(f"{namespace}:ResultReadyEventType")
            events = _Events()
            subscription = await client.create_subscription(50, events)
            await subscription.subscribe_events(vision, event_type)
            assert await asyncio.to_thread(subscriber.subscribed.wait, 20)
            job, scan = _scan_job(worker_tracker, None, "billet-21")
            worker_tracker.start(job, "worker-host:7")
            worker_tracker.succeed(job, {})
            await _wait_for(lambda: len(events.received) >= 1)
            await asyncio.sleep(0.5)  # no second event for the same result
            assert [(e["ResultId"], e["PartId"], e["JobId"]) for e in events.received] == [(scan, "billet-21", job)]

    with OpcUaServer(endpoint, sessions, "station1") as server, \
            JobStateSubscriber("127.0.0.1", 1883, prefix, server.notify) as subscriber:
        asyncio.run(client_side(subscriber))
    worker_tracker.publisher.close()
