"""The OPC UA server (OPC 40100-1 Machine Vision) driven by an asyncua client acting as an MES, signed and
encrypted, on SQLite and PostgreSQL: the NodeSet's VisionSystemType instance, each mandatory method of the Basic
Vision System Server profile with the specification's arguments and behaviour, its events, the errors of bad
arguments (which change nothing), the API keys' scopes, and the results of workers heard over MQTT. The jobs'
worker is played by the job tracker (``start``, ``progress``, ``succeed``), as the scan actor's bookkeeping does."""

import asyncio
import socket
import threading
import time
import uuid
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from asyncua import ua
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from asyncua.ua import uaerrors
from sqlalchemy import func, select

from services.db.apikeys import create_api_key, revoke_api_key
from services.db.engine import make_engine, make_sessions, migrate
from services.db.models import CalibrationSet, Job, PartType, Scan
from services.errors import InputError
from services.events.job_states import JobStateSubscriber
from services.events.mqtt import EventPublisher
from services.jobs.tracker import JobTracker
from services.opcua.security import KEY_CACHE_S
from services.opcua.server import NODESET, OpcUaServer, ServerOptions
from services.opcua.station import Station
from tests.conftest import POSTGRES_URL
from tests.opcua.mes import METHOD_PLACES, Mes, client_certificate, value

STATION = "station1"
I32, U32 = ua.VariantType.Int32, ua.VariantType.UInt32
NO_PARAMETERS = ua.Variant([], ua.VariantType.Variant)


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class Plant:
    """A station's database, its job tracker (the worker's bookkeeping), its OPC UA server and API keys."""

    def __init__(self, sessions, directory: Path, security_policy: str = "Basic256Sha256") -> None:
        self.sessions, self.directory = sessions, directory
        self.tracker = JobTracker(sessions)
        with sessions.begin() as session:
            session.add_all([
                CalibrationSet(id="c1", name="true rig", station=STATION, source="upload", active=True,
                               rig_sha256="r" * 64),
                CalibrationSet(id="c2", name="recalibrated", station=STATION, source="calibration",
                               rig_sha256="s" * 64),
                CalibrationSet(id="c3", name="pending", station=STATION, source="upload"),
                CalibrationSet(id="cx", name="other station's", station="station2", source="upload",
                               rig_sha256="t" * 64),
                PartType(id="billet", name="billet-90", station=STATION, material="carbon-steel",
                         part_sha256="a" * 64, mesh_sha256="b" * 64),
                PartType(id="shaft", name="shaft-40", station=STATION, material="stainless-steel",
                         part_sha256="c" * 64, mesh_sha256="d" * 64),
                PartType(id="foreign", name="gear", station="station2", material="carbon-steel",
                         part_sha256="e" * 64, mesh_sha256="f" * 64)])
            self.keys = {scope: create_api_key(session, f"mes {scope}", [scope])[1] for scope in ("read", "operate",
                                                                                                  "admin")}
        self.options = ServerOptions(f"opc.tcp://127.0.0.1:{_free_port()}/thermofield", pki_dir=directory / "pki",
                                     security_policy=security_policy)
        self.server = OpcUaServer(self.options, Station(sessions, STATION, self.tracker, None, queue_bound=5))
        self.certificate = asyncio.run(client_certificate(directory / "mes", self.options.trusted_dir))

    def mes(self, scope: str = "admin", **kwargs) -> Mes:
        return Mes(self.options.endpoint, self.keys[scope], self.certificate, **kwargs)

    def snapshot(self) -> dict:
        """What a failed call must not change: jobs, scans, the prepared part type, the active calibration."""
        with self.sessions() as session:
            return {"jobs": session.scalar(select(func.count()).select_from(Job)),
                    "scans": session.scalar(select(func.count()).select_from(Scan)),
                    "selected": sorted(session.scalars(select(PartType.id).where(PartType.selected.is_(True)))),
                    "active": sorted(session.scalars(select(CalibrationSet.id).where(CalibrationSet.active.is_(True))))}

    def work(self, job_id: str, result: dict | None = None, fail: str | None = None) -> None:
        """A worker runs the job: capture, then processing, then its result (or failure)."""
        self.tracker.start(job_id, "worker:1")
        self.tracker.progress(job_id, "capture", 0.05)
        self.tracker.progress(job_id, "reconstruct", 0.3)
        if fail:
            self.tracker.fail(job_id, fail, will_retry=False)
        else:
            self.tracker.succeed(job_id, result or {})


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def plant(request, tmp_path_factory):
    directory = tmp_path_factory.mktemp("plant")
    if request.param == "sqlite":
        engine = make_engine(f"sqlite:///{directory / 'service.db'}")
    else:
        schema = f"tf_test_{uuid.uuid4().hex[:12]}"
        engine = make_engine(POSTGRES_URL, schema)
    migrate(engine)
    plant = Plant(make_sessions(engine), directory)
    with plant.server:
        plant.tracker.listeners.append(plant.server.notify)
        yield plant
    engine.dispose()
    if request.param == "postgresql":
        from sqlalchemy import text
        with make_engine(POSTGRES_URL).begin() as connection:
            connection.execute(text(f"DROP SCHEMA {schema} CASCADE"))


async def _restart(mes: Mes) -> None:
    """Reset, then into automatic mode (each test starts there, whatever the one before left)."""
    await mes.call("Reset", ua.Variant(0, I32), "next test")
    await mes.call("SelectModeAutomatic")


def _id(cls: str, text: str):
    return getattr(ua, cls)(Id=text)


def _start_args(recipe: str | None = "billet-90", part: str = "part-1", meas: str = "meas-1"):
    return (_id("MeasIdDataType", meas), _id("PartIdDataType", part),
            None if recipe is None else _id("RecipeIdExternalDataType", recipe), None, NO_PARAMETERS)


def test_an_mes_prepares_a_recipe_starts_a_job_and_reads_its_result(plant):
    async def mes_side():
        async with plant.mes() as mes:
            await _restart(mes)
            await mes.subscribe("ResultReadyEventType", "StateChangedEventType", "JobStartedEventType",
                                "ReadyEventType", "AcquisitionDoneEventType", "RecipePreparedEventType")
            # list the recipes (the station's part types only), prepare one
            complete, count, _, recipes, error = await mes.call("GetRecipeListFiltered", None, None,
                                                                ua.Variant(2, I32), ua.Variant(0, U32),
                                                                ua.Variant(0, U32), ua.Variant(0, I32))
            assert (complete, count, error) == (True, 2, 0)
            assert [recipe.Id for recipe in recipes] == ["billet", "shaft"]
            internal, completed, error = await mes.call("PrepareRecipe", _id("RecipeIdExternalDataType", "billet-90"),
                                                        None)
            assert (internal.Id, completed, error) == ("billet", True, 0)
            assert await mes.state() == ("Operational", "Ready")
            assert plant.snapshot()["selected"] == ["billet"]
            prepared = await mes.call("GetRecipeListFiltered", None, None, ua.Variant(1, I32), ua.Variant(0, U32),
                                      ua.Variant(0, U32), ua.Variant(0, I32))
            assert [recipe.Id for recipe in prepared[3]] == ["billet"]

            # a single job: a scan of the station with the prepared recipe, its result announced
            job, error = await mes.call("StartSingleJob", *_start_args(part="forging-7", meas="run-1"))
            assert error == 0 and await mes.state() == ("Operational", "SingleExecution")
            with plant.sessions() as session:
                scan = session.scalar(select(Scan).where(Scan.job_id == job.Id))
                assert (scan.part_id, scan.part_type_id, scan.calibration_set_id) == ("forging-7", "billet", "c1")
            plant.work(job.Id, {"verdict": "NotOK", "features": [{"name": "body_diameter", "deviation": 0.7}],
                                "stage_seconds": {"capture": 1.5, "reconstruct": 0.5}})
            assert await mes.wait_for(lambda: mes.of_type("ResultReadyEventType"))
            (ready,) = mes.of_type("ResultReadyEventType")
            assert value(ready, "ResultId").Id == scan.id and value(ready, "JobId").Id == job.Id
            assert (value(ready, "ResultState"), value(ready, "IsPartial")) == (1, False)  # Completed
            assert [v.Value for v in value(ready, "ResultContent")][0] == "NotOK"
            assert (value(ready, "PartId").Id, value(ready, "MeasId").Id) == ("forging-7", "run-1")
            assert value(ready, "InternalRecipeId").Id == "billet"
            assert value(ready, "InternalConfigurationId").Id == "c1"
            assert await mes.wait_for(lambda: mes.of_type("ReadyEventType"))
            assert await mes.state() == ("Operational", "Ready")
            assert [value(e, "JobId").Id for e in mes.of_type("JobStartedEventType")] == [job.Id]
            assert [value(e, "JobId").Id for e in mes.of_type("AcquisitionDoneEventType")] == [job.Id]
            assert [value(e, "InternalId").Id for e in mes.of_type("RecipePreparedEventType")] == ["billet"]
            assert [value(e, "Transition").Text for e in mes.of_type("StateChangedEventType")][-3:] == [
                "InitializedToReadyRecipe", "ReadyToSingleExecution", "SingleExecutionToReadyAuto"]

            # the result, whole and by components, and in the filtered list
            _, result, error = await mes.call("GetResultById", _id("ResultIdDataType", scan.id), ua.Variant(0, I32))
            assert error == 0 and result.ResultId.Id == scan.id and result.ResultState == 1
            assert result.ResultContent[0].Value == "NotOK" and "body_diameter" in result.ResultContent[1].Value
            assert result.ProcessingTimes.AcquisitionDuration == pytest.approx(1500.0)
            components = await mes.call("GetResultComponentsById", _id("ResultIdDataType", scan.id), ua.Variant(0, I32))
            assert components[4] == 1 and components[6].Id == "forging-7" and components[12].Id == job.Id
            listed = await mes.call("GetResultListFiltered", ua.Variant(0, I32), _id("MeasIdDataType", "run-1"), None,
                                    None, None, None, None, None, None, ua.Variant(10, U32), ua.Variant(0, U32),
                                    ua.Variant(0, I32))
            assert [r.ResultId.Id for r in listed[3]] == [scan.id] and listed[:2] == [True, 1]
            # unprepared: Initialized, and no job can start
            await mes.call("UnprepareRecipe", None, _id("RecipeIdInternalDataType", "billet"))
            assert await mes.state() == ("Operational", "Initialized") and plant.snapshot()["selected"] == []

    asyncio.run(mes_side())


def _spec_arguments() -> dict[str, tuple[list, list]]:
    """Each mandatory method's InputArguments and OutputArguments (name, DataType) as the NodeSet's types declare
    them, read from the XML itself."""
    ns = {"u": "http://opcfoundation.org/UA/2011/03/UANodeSet.xsd",
          "t": "http://opcfoundation.org/UA/2008/02/Types.xsd"}
    root = ET.parse(NODESET).getroot()
    nodes = {node.get("NodeId"): node for node in root if node.get("NodeId")}
    owners = {"VisionStateMachine": "1:VisionStateMachineType", "AutomaticModeStateMachine":
              "1:VisionAutomaticModeStateMachineType", "RecipeManagement": "1:RecipeManagementType",
              "ConfigurationManagement": "1:ConfigurationManagementType", "ResultManagement": "1:ResultManagementType"}
    spec = {}
    for name, place in METHOD_PLACES.items():
        owner = next(nid for nid, node in nodes.items() if node.get("BrowseName") == owners[place[-1]])
        method = next(node for node in nodes.values() if node.get("ParentNodeId") == owner
                      and node.get("BrowseName") == f"1:{name}" and node.tag.endswith("UAMethod"))
        arguments = {}
        for reference in method.find("u:References", ns):
            if reference.get("ReferenceType") == "HasProperty":
                prop = nodes[reference.text]
                arguments[prop.get("BrowseName")] = [
                    (a.find("t:Name", ns).text, a.find("t:DataType/t:Identifier", ns).text)
                    for a in prop.iter("{%s}Argument" % ns["t"])]
        spec[name] = (arguments.get("InputArguments", []), arguments.get("OutputArguments", []))
    return spec


def test_each_mandatory_method_exists_on_the_instance_with_the_specification_arguments(plant):
    spec = _spec_arguments()
    assert len(spec) == 16

    async def mes_side():
        async with plant.mes("read") as mes:
            for name, (inputs, outputs) in spec.items():
                method = await mes.method(name)
                assert (await method.read_node_class()) == ua.NodeClass.Method, name
                declared = {}
                for prop in ("InputArguments", "OutputArguments"):
                    try:
                        arguments = await (await method.get_child(f"0:{prop}")).read_value()
                    except uaerrors.BadNoMatch:
                        arguments = []
                    declared[prop] = [(a.Name, a.DataType.to_string().replace(f"ns={mes.mv};", "ns=1;"))
                                      for a in arguments]
                assert declared["InputArguments"] == inputs, name
                assert declared["OutputArguments"] == outputs, name
                assert (await method.read_attribute(ua.AttributeIds.Executable)).Value.Value is True, name

    asyncio.run(mes_side())


def test_the_state_machine_halts_resets_and_refuses_jobs_while_halted(plant):
    async def mes_side():
        async with plant.mes() as mes:
            await _restart(mes)
            await mes.call("PrepareRecipe", _id("RecipeIdExternalDataType", "shaft-40"), None)
            assert await mes.state() == ("Operational", "Ready")
            await mes.subscribe("StateChangedEventType")
            assert await mes.call("Halt", ua.Variant(0, I32), "shift ends") == [0]
            assert await mes.state() == ("Halted", None)
            before = plant.snapshot()
            for method, arguments in (("StartSingleJob", _start_args("shaft-40")),
                                      ("StartContinuous", _start_args("shaft-40")),
                                      ("PrepareRecipe", (_id("RecipeIdExternalDataType", "billet-90"), None)),
                                      ("SelectModeAutomatic", ()),
                                      ("ActivateConfiguration", (_id("ConfigurationIdDataType", "c2"),))):
                with pytest.raises(uaerrors.BadInvalidState):
                    await mes.call(method, *arguments)
            assert plant.snapshot() == before
            assert await mes.call("Halt", ua.Variant(0, I32), "") == [0]  # always executable
            assert await mes.call("Stop", ua.Variant(0, I32), "") == [0]
            await mes.call("Reset", ua.Variant(1, I32), "shift starts")
            assert await mes.state() == ("Preoperational", None)
            await mes.call("SelectModeAutomatic")
            assert await mes.state() == ("Operational", "Ready")  # the prepared recipe stays prepared
            with pytest.raises(uaerrors.BadInvalidState):
                await mes.call("SelectModeAutomatic")
            assert await mes.wait_for(lambda: len(mes.of_type("StateChangedEventType")) >= 4)
            assert [value(e, "Transition").Text for e in mes.of_type("StateChangedEventType")][:4] == [
                "OperationalToHalted", "HaltedToPreoperational", "PreoperationalToInitialized",
                "InitializedToReadyAuto"]

    asyncio.run(mes_side())


def test_continuous_execution_scans_until_stopped_and_abort_cancels_what_is_queued(plant):
    def scan_jobs() -> list[Job]:
        with plant.sessions() as session:
            return list(session.scalars(select(Job).where(Job.kind == "scan").order_by(Job.created_at)))

    async def mes_side():
        async with plant.mes() as mes:
            await _restart(mes)
            await mes.call("PrepareRecipe", _id("RecipeIdExternalDataType", "billet-90"), None)
            await mes.subscribe("ResultReadyEventType")
            known = {job.id for job in scan_jobs()}
            run, error = await mes.call("StartContinuous", *_start_args(part="coil", meas="web-1"))
            assert error == 0 and await mes.state() == ("Operational", "ContinuousExecution")
            for scans in (1, 2):  # each finished scan starts the next
                new = [job for job in scan_jobs() if job.id not in known]
                assert len(new) == scans and new[-1].params["opcua_job_id"] == run.Id
                await asyncio.to_thread(plant.work, new[-1].id, {"verdict": "OK"})
                assert await mes.wait_for(lambda: len(mes.of_type("ResultReadyEventType")) >= scans)
                assert await mes.wait_for(lambda: len([j for j in scan_jobs() if j.id not in known]) == scans + 1)
            assert {value(e, "JobId").Id for e in mes.of_type("ResultReadyEventType")} == {run.Id}
            await mes.call("Stop", ua.Variant(0, I32), "end of coil")
            assert await mes.state() == ("Operational", "Ready")
            last = [job for job in scan_jobs() if job.id not in known][-1]
            await asyncio.to_thread(plant.work, last.id, {"verdict": "OK"})  # the scan under way keeps its result
            assert await mes.wait_for(lambda: len(mes.of_type("ResultReadyEventType")) == 3)
            await asyncio.sleep(0.5)  # the test's window: a scan started after Stop would be there by now
            assert len([job for job in scan_jobs() if job.id not in known]) == 3  # none after Stop
            results = await mes.call("GetResultListFiltered", ua.Variant(0, I32), None, None, None, None, None, None,
                                     None, _id("JobIdDataType", run.Id), ua.Variant(0, U32), ua.Variant(0, U32),
                                     ua.Variant(0, I32))
            assert results[1] == 3 and {r.ResultState for r in results[3]} == {1}

            # Abort: the queued scan is cancelled (never run by a worker), its result Aborted
            job, _ = await mes.call("StartSingleJob", *_start_args())
            await mes.call("Abort", ua.Variant(0, I32), "part missing")
            assert await mes.state() == ("Operational", "Ready")
            with plant.sessions() as session:
                aborted = session.get(Job, job.Id)
                scan_id = session.scalar(select(Scan.id).where(Scan.job_id == job.Id))
            assert aborted.status == "failed" and plant.tracker.start(job.Id, "worker:2") is None
            _, result, _ = await mes.call("GetResultById", _id("ResultIdDataType", scan_id), ua.Variant(0, I32))
            assert result.ResultState == 3

    asyncio.run(mes_side())


def test_configurations_are_the_calibration_sets(plant):
    async def mes_side():
        async with plant.mes() as mes:
            await _restart(mes)
            complete, count, _, configurations, error = await mes.call(
                "GetConfigurationList", ua.Variant(2, U32), ua.Variant(0, U32), ua.Variant(0, I32))
            assert (complete, count, error) == (False, 2, 0)  # two of the station's three
            rest = await mes.call("GetConfigurationList", ua.Variant(2, U32), ua.Variant(2, U32), ua.Variant(0, I32))
            assert rest[:2] == [True, 1]
            assert [c.InternalId.Id for c in configurations + rest[3]] == ["c1", "c2", "c3"]
            _, configuration, _ = await mes.call("GetConfigurationById", _id("ConfigurationIdDataType", "c2"),
                                                 ua.Variant(0, I32))
            assert configuration.ExternalId.Id == "recalibrated"
            assert await mes.call("ActivateConfiguration", _id("ConfigurationIdDataType", "c2")) == [0]
            assert plant.snapshot()["active"] == ["c2"]
            active = await (await mes.vision.get_child([f"{mes.mv}:ConfigurationManagement",
                                                        f"{mes.mv}:ActiveConfiguration"])).read_value()
            assert active.InternalId.Id == "c2"
            before = plant.snapshot()
            for configuration_id, status in (("c3", uaerrors.BadInvalidArgument), ("cx", uaerrors.BadInvalidArgument),
                                             ("nope", uaerrors.BadInvalidArgument)):
                with pytest.raises(status):  # no rig yet; another station's; none
                    await mes.call("ActivateConfiguration", _id("ConfigurationIdDataType", configuration_id))
            assert plant.snapshot() == before
            await mes.call("ActivateConfiguration", _id("ConfigurationIdDataType", "c1"))

    asyncio.run(mes_side())


def test_bad_arguments_answer_the_specification_errors_and_change_nothing(plant):
    async def mes_side():
        async with plant.mes() as mes:
            await _restart(mes)
            await mes.call("PrepareRecipe", _id("RecipeIdExternalDataType", "billet-90"), None)
            await mes.subscribe("VisionWarningConditionType")
            before = plant.snapshot()
            cases = [  # method, arguments, status, per-argument status (index, code)
                ("PrepareRecipe", (_id("RecipeIdExternalDataType", "no such part"), None), "BadInvalidArgument",
                 (0, "BadNotFound")),
                ("PrepareRecipe", (None, _id("RecipeIdInternalDataType", "foreign")), "BadInvalidArgument",
                 (1, "BadNotFound")),  # another station's
                ("UnprepareRecipe", (_id("RecipeIdExternalDataType", "x" * 300), None), "BadInvalidArgument",
                 (0, "BadOutOfRange")),
                ("StartSingleJob", _start_args("shaft-40"), "BadInvalidArgument", (2, "BadNotFound")),  # not prepared
                ("StartSingleJob", _start_args(part="p" * 300), "BadInvalidArgument", (1, "BadOutOfRange")),
                ("StartSingleJob", (*_start_args()[:4], ua.Variant([ua.Variant(1.5)], ua.VariantType.Variant)),
                 "BadInvalidArgument", (4, "BadOutOfRange")),  # the station's recipes take no parameters
                ("StartSingleJob", ("garbage", *_start_args()[1:]), "BadInvalidArgument", (0, "BadTypeMismatch")),
                ("StartSingleJob", _start_args()[:3], "BadArgumentsMissing", None),
                ("StartSingleJob", (*_start_args(), "extra"), "BadTooManyArguments", None),
                ("Halt", (ua.Variant("soon", ua.VariantType.String), ""), "BadInvalidArgument", (0, "BadTypeMismatch")),
                ("GetResultById", (_id("ResultIdDataType", "no such scan"), ua.Variant(0, I32)), "BadInvalidArgument",
                 (0, "BadNotFound")),
                ("GetRecipeListFiltered", (None, None, ua.Variant(7, I32), ua.Variant(0, U32), ua.Variant(0, U32),
                                           ua.Variant(0, I32)), "BadInvalidArgument", (2, "BadInvalidArgument")),
                ("GetConfigurationById", (_id("ConfigurationIdDataType", "cx"), ua.Variant(0, I32)),
                 "BadInvalidArgument", (0, "BadNotFound")),
            ]
            for method, arguments, status, argument in cases:
                result = await mes.call_raw(method, *arguments)
                assert result.StatusCode.value == getattr(ua.StatusCodes, status), (method, result.StatusCode)
                if argument is not None:
                    index, code = argument
                    assert result.InputArgumentResults[index].value == getattr(ua.StatusCodes, code), method
                assert plant.snapshot() == before, method
            assert await mes.state() == ("Operational", "Ready")
            # each failure is also a warning message naming the method and its arguments (OPC 40100-1, 11.5)
            assert await mes.wait_for(lambda: len(mes.of_type("VisionWarningConditionType")) == len(cases))
            warnings = [value(e, "Message").Text for e in mes.of_type("VisionWarningConditionType")]
            assert [w.split("(", 1)[0] for w in warnings] == [method for method, *_ in cases]
            assert "'no such part'" in warnings[0] and value(mes.of_type("VisionWarningConditionType")[0],
                                                             "ErrorString") == "BadInvalidArgument"

    asyncio.run(mes_side())


def test_api_key_scopes_decide_the_methods_and_only_trusted_clients_connect_signed_and_encrypted(plant, tmp_path):
    async def mes_side():
        async with plant.mes("read") as reader:
            assert (await reader.call("GetRecipeListFiltered", None, None, ua.Variant(2, I32), ua.Variant(0, U32),
                                      ua.Variant(0, U32), ua.Variant(0, I32)))[1] == 2
            before = plant.snapshot()
            for method, arguments in (("StartSingleJob", _start_args()), ("Halt", (ua.Variant(0, I32), "")),
                                      ("PrepareRecipe", (_id("RecipeIdExternalDataType", "shaft-40"), None))):
                with pytest.raises(uaerrors.BadUserAccessDenied):
                    await reader.call(method, *arguments)
            assert plant.snapshot() == before
        async with plant.mes("operate") as operator:
            with pytest.raises(uaerrors.BadUserAccessDenied):  # selecting a part type needs admin, as over HTTP
                await operator.call("PrepareRecipe", _id("RecipeIdExternalDataType", "shaft-40"), None)
            assert await operator.call("Stop", ua.Variant(0, I32), "") == [0]
        with plant.sessions.begin() as session:
            revoked, secret = create_api_key(session, "revoked MES", ["operate"])
        async with Mes(plant.options.endpoint, secret, plant.certificate) as mes:
            assert await mes.call("Stop", ua.Variant(0, I32), "") == [0]
            with plant.sessions.begin() as session:
                revoke_api_key(session, revoked.id)
            await asyncio.sleep(KEY_CACHE_S + 0.5)  # a revoked key stops working within the cache time
            with pytest.raises(uaerrors.BadUserAccessDenied):
                await mes.call("Stop", ua.Variant(0, I32), "")
        with pytest.raises(Exception):  # an unknown key is refused
            async with Mes(plant.options.endpoint, "tf_not-a-key", plant.certificate):
                pass
        stranger = await client_certificate(tmp_path / "stranger", None)  # never copied into trusted/
        with pytest.raises(Exception):
            async with Mes(plant.options.endpoint, plant.keys["admin"], stranger):
                pass
        with pytest.raises(Exception):  # no security: not offered
            async with Mes(plant.options.endpoint, plant.keys["admin"], None):
                pass
        async with plant.mes("read") as reader:  # the endpoints offered: Basic256Sha256 Sign&Encrypt only
            endpoints = await reader.client.uaclient.get_endpoints(
                ua.GetEndpointsParameters(EndpointUrl=plant.options.endpoint))
            assert {(e.SecurityPolicyUri.rsplit("#", 1)[1], e.SecurityMode) for e in endpoints} == {
                ("Basic256Sha256", ua.MessageSecurityMode.SignAndEncrypt)}
            assert {t.TokenType for e in endpoints for t in e.UserIdentityTokens} == {ua.UserTokenType.UserName}

    asyncio.run(mes_side())


def test_no_security_only_when_set_and_still_with_an_api_key(tmp_path):
    engine = make_engine(f"sqlite:///{tmp_path / 'service.db'}")
    migrate(engine)
    plant = Plant(make_sessions(engine), tmp_path, security_policy="None")

    async def mes_side():
        async with Mes(plant.options.endpoint, plant.keys["read"]) as mes:
            endpoints = await mes.client.uaclient.get_endpoints(
                ua.GetEndpointsParameters(EndpointUrl=plant.options.endpoint))
            assert {(e.SecurityPolicyUri.rsplit("#", 1)[1], e.SecurityMode) for e in endpoints} == {
                ("None", ua.MessageSecurityMode.None_)}
            assert (await mes.call("GetRecipeListFiltered", None, None, ua.Variant(2, I32), ua.Variant(0, U32),
                                   ua.Variant(0, U32), ua.Variant(0, I32)))[1] == 2
        with pytest.raises(Exception):
            async with Mes(plant.options.endpoint, "tf_not-a-key"):
                pass

    with plant.server:
        assert plant.server.certificate is None
        asyncio.run(mes_side())
    assert not (tmp_path / "pki" / "server-certificate.der").exists()  # no certificate made


class _SlowStation(Station):
    """A station whose next recipe list, once ``slow`` is set, is read and then returned a second later (a
    database under load): the read is stale by the time the server gets it."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.slow, self.reading = False, threading.Event()

    def recipes(self):
        rows = super().recipes()
        if self.slow:  # once: the refresh's read, not the method's own
            self.slow = False
            self.reading.set()
            time.sleep(1.0)
        return rows


def test_a_recipe_prepared_while_the_periodic_refresh_reads_stays_prepared(tmp_path):
    engine = make_engine(f"sqlite:///{tmp_path / 'service.db'}")
    migrate(engine)
    plant = Plant(make_sessions(engine), tmp_path, security_policy="None")
    station = _SlowStation(plant.sessions, STATION, plant.tracker, None, queue_bound=5)
    plant.server = OpcUaServer(plant.options, station)

    async def mes_side():
        async with Mes(plant.options.endpoint, plant.keys["admin"]) as mes:
            await _restart(mes)
            station.slow = True
            assert await asyncio.to_thread(station.reading.wait, 10)  # the refresh (every 2 s) is reading
            await mes.call("PrepareRecipe", _id("RecipeIdExternalDataType", "billet-90"), None)
            await asyncio.sleep(1.5)  # the stale read has come back
            assert await mes.state() == ("Operational", "Ready")
            _, error = await mes.call("StartSingleJob", *_start_args())
            assert error == 0

    with plant.server:
        asyncio.run(mes_side())


# The endpoint's checks touch no row: one database is enough.
@pytest.mark.parametrize("engine", ["sqlite"], indirect=True)
def test_a_bad_endpoint_or_a_taken_port_is_a_clear_error(engine, tmp_path):
    station = Station(make_sessions(engine), STATION, JobTracker(make_sessions(engine)), None)
    with pytest.raises(InputError, match="not an opc.tcp://host:port"):
        OpcUaServer(ServerOptions("http://127.0.0.1:4840", pki_dir=tmp_path), station)
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        options = ServerOptions(f"opc.tcp://127.0.0.1:{busy.getsockname()[1]}/thermofield", pki_dir=tmp_path)
        with pytest.raises(InputError, match="cannot listen"):
            with OpcUaServer(options, station):
                pass
    with pytest.raises(InputError, match="go together"):
        with OpcUaServer(ServerOptions(f"opc.tcp://127.0.0.1:{_free_port()}/x", pki_dir=tmp_path,
                                       certificate=tmp_path / "cert.der"), station):
            pass


def test_scaled_out_the_workers_results_reach_the_mes_over_mqtt(tmp_path):
    """``thermofield api`` runs no jobs: the workers' trackers publish the states on MQTT, the API's subscriber
    feeds its OPC UA server, which raises ResultReady and returns to Ready as embedded."""
    engine = make_engine(f"sqlite:///{tmp_path / 'service.db'}")
    migrate(engine)
    plant = Plant(make_sessions(engine), tmp_path)
    prefix = f"test-{uuid.uuid4().hex[:8]}/{STATION}"
    worker = JobTracker(plant.sessions, EventPublisher("127.0.0.1", 1883, prefix))
    api = JobTracker(plant.sessions, EventPublisher("127.0.0.1", 1883, prefix))
    plant.server.station.tracker = api

    async def mes_side(subscriber: JobStateSubscriber):
        assert await asyncio.to_thread(subscriber.subscribed.wait, 20)
        async with plant.mes() as mes:
            await mes.call("PrepareRecipe", _id("RecipeIdExternalDataType", "billet-90"), None)
            await mes.subscribe("ResultReadyEventType")
            job, _ = await mes.call("StartSingleJob", *_start_args(part="billet-21"))
            assert await mes.state() == ("Operational", "SingleExecution")
            for step in (lambda: worker.start(job.Id, "worker-host:7"),
                         lambda: worker.progress(job.Id, "reconstruct", 0.3),
                         lambda: worker.succeed(job.Id, {"verdict": "OK"})):
                await asyncio.to_thread(step)
            assert await mes.wait_for(lambda: mes.of_type("ResultReadyEventType"))
            await asyncio.sleep(0.5)  # no second event for the same result
            (event,) = mes.of_type("ResultReadyEventType")
            assert (value(event, "PartId").Id, value(event, "JobId").Id) == ("billet-21", job.Id)
            assert await mes.state() == ("Operational", "Ready")

    with plant.server as server, JobStateSubscriber("127.0.0.1", 1883, prefix, server.notify) as subscriber:
        asyncio.run(mes_side(subscriber))
    worker.publisher.close()
    api.publisher.close()


_ANSWERS = {getattr(ua.StatusCodes, name) for name in (
    "Good", "BadInvalidArgument", "BadArgumentsMissing", "BadTooManyArguments", "BadInvalidState",
    "BadResourceUnavailable")}
_STRUCTS = ("MeasIdDataType", "PartIdDataType", "RecipeIdExternalDataType", "RecipeIdInternalDataType",
            "ProductIdDataType", "ConfigurationIdDataType", "ResultIdDataType", "JobIdDataType")
_TEXT = st.text(max_size=300) | st.sampled_from(["billet-90", "billet", "c1", "", "x" * 256, "a\x00b"])
_VARIANTS = st.one_of(
    st.none().map(ua.Variant),
    st.integers(-2 ** 31, 2 ** 31 - 1).map(lambda i: ua.Variant(i, I32)),
    st.integers(0, 2 ** 32 - 1).map(lambda i: ua.Variant(i, U32)),
    st.floats(allow_nan=False).map(lambda f: ua.Variant(f, ua.VariantType.Double)),
    st.booleans().map(lambda b: ua.Variant(b, ua.VariantType.Boolean)),
    _TEXT.map(lambda t: ua.Variant(t, ua.VariantType.String)),
    st.tuples(st.sampled_from(_STRUCTS), _TEXT).map(lambda s: ua.Variant(getattr(ua, s[0])(Id=s[1]))),
    st.lists(st.integers(0, 9).map(lambda i: ua.Variant(i, I32)), max_size=3).map(
        lambda items: ua.Variant(items, ua.VariantType.Variant)))


def test_garbage_calls_get_a_status_never_an_internal_error_and_failures_change_nothing(plant):
    """Any method with any arguments (types, counts, lengths, control characters): a Call status of the
    specification, never Bad_InternalError or Bad_UnexpectedError, and a call that fails changes nothing."""
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()

    def run(coroutine):
        return asyncio.run_coroutine_threadsafe(coroutine, loop).result(60)

    mes = plant.mes()
    run(mes.__aenter__())
    try:
        run(_restart(mes))

        @settings(max_examples=150, deadline=None, suppress_health_check=list(HealthCheck))
        @given(method=st.sampled_from(sorted(METHOD_PLACES)), arguments=st.lists(_VARIANTS, max_size=13))
        def call(method, arguments):
            before = plant.snapshot()
            result = run(mes.call_raw(method, *arguments))
            assert result.StatusCode.value in _ANSWERS, (method, arguments, result.StatusCode)
            if not result.StatusCode.is_good():
                assert plant.snapshot() == before, (method, arguments)

        call()
    finally:
        run(mes.__aexit__(None, None, None))
        loop.call_soon_threadsafe(loop.stop)
        thread.join(10)
