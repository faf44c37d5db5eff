"""The station's OPC UA server: the OPC Foundation's Machine Vision information model (OPC 40100-1) with one
``VisionSystemType`` object for the station, and the Basic Vision System Server profile's mandatory methods
backed by the service (docs/opcua.md).

The server runs its own asyncio loop in a thread of the process that serves the API (``thermofield serve``
embedded, ``thermofield api`` scaled out). It follows the station's scan jobs through the job states the
process hears (:meth:`OpcUaServer.notify`: the embedded job tracker's listener, or the workers' MQTT states)
and reads recipes, configurations and results from the database, so that it sees every worker's jobs.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import threading
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from services.errors import InputError
from services.jobs.scans import JobRefused
from services.opcua.security import ApiKeyUsers, CallerRuleset, caller, METHOD_SCOPES
from services.opcua.station import Configuration, Recipe, Result, ResultFilter, Station, result_state

logger = logging.getLogger(__name__)

NODESET = Path(__file__).with_name("Opc.Ua.MachineVision.NodeSet2.xml")
"""OPC 40100-1's NodeSet as the OPC Foundation publishes it (MIT licence, its notice in the file)."""
MACHINE_VISION = "http://opcfoundation.org/UA/MachineVision"
NAMESPACE = "urn:thermofield:machine-vision"
"""The namespace of the station's instance nodes (the types are in ``MACHINE_VISION``)."""
REFRESH_S = 2.0
"""How often recipes (the prepared one) and the active configuration are re-read from the database."""
MAX_TEXT = 255
"""Longest string a method takes (an id, a cause's description)."""
MAX_RESULTS = 1000
"""Most entries one list method returns (MaxResults 0 asks for as many)."""
MAX_WAIT_MS = 30_000
"""Longest a GetResult method waits for a result still processing (its Timeout argument, in ms)."""
_START_TIMEOUT_S = 60.0
_PREFETCHED = 1000
_ACQUIRING_STAGES = ("queued", "starting", "capture", "retrying", "recovered")


class MethodError(Exception):
    """A method call that failed: its status code and, for bad arguments, each input argument's status."""

    def __init__(self, status: int, message: str, argument_results: dict[int, int] | None = None) -> None:
        super().__init__(message)
        self.status, self.argument_results = status, argument_results or {}


@dataclass(frozen=True)
class ServerOptions:
    """Where and how the server listens (from the ``THERMOFIELD_OPCUA_*`` settings)."""

    endpoint: str
    pki_dir: Path
    security_policy: str = "Basic256Sha256"
    certificate: Path | None = None
    private_key: Path | None = None

    @classmethod
    def from_settings(cls, settings) -> ServerOptions:
        return cls(settings.opcua_endpoint, settings.opcua_pki_dir or settings.data_dir / "opcua",
                   settings.opcua_security_policy, settings.opcua_certificate, settings.opcua_private_key)

    @property
    def trusted_dir(self) -> Path:
        return self.pki_dir / "trusted"


class OpcUaServer:
    """The station's OPC UA server, started as a context manager.

    Parameters
    ----------
    options : ServerOptions
        The endpoint (``opc.tcp://host:port/path``; the server binds its host and port) and security.
    station : Station
        The station's database, job tracker and outbox.
    """

    def __init__(self, options: ServerOptions, station: Station) -> None:
        address = urlsplit(options.endpoint)
        if address.scheme != "opc.tcp" or not address.hostname or address.port is None:
            raise InputError(f"THERMOFIELD_OPCUA_ENDPOINT: {options.endpoint!r} is not an opc.tcp://host:port/... URL")
        self.options, self.station, self.endpoint = options, station, options.endpoint
        self.users = ApiKeyUsers(station.sessions)
        self.certificate: Path | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._states: asyncio.Queue | None = None
        self._stop: asyncio.Event | None = None
        self._started = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="opcua-server", daemon=True)

    def __enter__(self) -> OpcUaServer:
        self._thread.start()
        if not self._started.wait(_START_TIMEOUT_S):
            raise RuntimeError(f"the OPC UA server at {self.endpoint} did not start in {_START_TIMEOUT_S:g} s")
        if isinstance(self._error, InputError):
            raise self._error
        if self._error is not None:
            raise InputError(f"the OPC UA server cannot listen at {self.endpoint} ({self._error}); "
                             "is the port taken? set THERMOFIELD_OPCUA_ENDPOINT") from None
        return self

    def __exit__(self, *exc_info: object) -> None:
        if self._loop is not None and self._thread.is_alive():
            self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(timeout=10)

    def notify(self, state: dict[str, Any]) -> None:
        """Take a job state the process heard (thread-safe, never blocks); scan jobs move the state machines and,
        finished, raise ResultReady."""
        if state.get("kind") != "scan" or self._loop is None or not self._thread.is_alive():
            return
        self._loop.call_soon_threadsafe(self._states.put_nowait, state)

    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as error:  # reported to __enter__ when starting; logged afterwards
            if not self._started.is_set():
                self._error = error
                self._started.set()
            else:
                logger.exception("the OPC UA server stopped")

    async def _main(self) -> None:
        from asyncua import Server, ua

        from services.opcua.security import application_uri, load_server_certificate, trusted_clients_validator

        self._loop = asyncio.get_running_loop()
        self._states, self._stop = asyncio.Queue(), asyncio.Event()
        server = Server(user_manager=self.users)
        await server.init()
        server.set_endpoint(self.endpoint)
        server.set_server_name(f"thermofield {self.station.name}")
        await server.set_application_uri(application_uri(self.station.name))
        server.set_identity_tokens([ua.UserNameIdentityToken])
        if self.options.security_policy == "None":
            server.set_security_policy([ua.SecurityPolicyType.NoSecurity], permission_ruleset=CallerRuleset())
        else:
            host = urlsplit(self.endpoint).hostname
            self.certificate = await load_server_certificate(
                server, self.options.pki_dir, self.options.certificate, self.options.private_key, self.station.name,
                socket.gethostname() if host in ("0.0.0.0", "::") else host)
            server.set_security_policy([ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt],
                                       permission_ruleset=CallerRuleset())
            server.set_certificate_validator(trusted_clients_validator(self.options.trusted_dir))
        vision = await VisionSystem.build(server, self.station, self.users)
        async with server:
            await vision.start(await asyncio.to_thread(self.station.in_flight))
            self._started.set()
            refresh = asyncio.create_task(vision.refresh_forever())
            try:
                while not self._stop.is_set():
                    getter = asyncio.create_task(self._states.get())
                    stopper = asyncio.create_task(self._stop.wait())
                    done, _ = await asyncio.wait({getter, stopper}, return_when=asyncio.FIRST_COMPLETED)
                    stopper.cancel()
                    if getter not in done:
                        getter.cancel()
                        break
                    try:
                        await vision.on_job_state(getter.result())
                    except Exception:  # a bad state must not stop the server
                        logger.exception("OPC UA: could not follow a scan job's state")
            finally:
                refresh.cancel()


class VisionSystem:
    """The ``VisionSystemType`` object of the station: its state machines, methods and events."""

    def __init__(self, server, station: Station, users: ApiKeyUsers) -> None:
        self.server, self.station, self.users = server, station, users
        self.vision_state = "Preoperational"
        self.automatic_state: str | None = None
        self.prepared: Recipe | None = None
        # held while the prepared recipe is read from or written to the database, so that the periodic refresh
        # never replaces a recipe prepared during its read with the stale one it read
        self.recipe_lock = asyncio.Lock()
        self.acquiring: dict[str, str] = {}  # scan job id -> its OPC UA job id, while queued or capturing
        self.continuous: dict[str, Any] | None = None  # the continuous run: its job id, arguments, current scan job
        self.last_job = ""  # the OPC UA job whose acquisition ended last
        self.results: dict[str, asyncio.Task] = {}  # scan job id -> its result's rows, read while it runs
        self.starting = 0  # start methods under way (their jobs' first states are theirs to announce)
        self.nodes: dict[str, Any] = {}
        self.state_ids: dict[str, Any] = {}
        self.events: dict[str, Any] = {}

    # the address space

    @classmethod
    async def build(cls, server, station: Station, users: ApiKeyUsers) -> VisionSystem:
        from asyncua import ua
        from asyncua.common.copy_node_util import copy_node
        from asyncua.common.instantiate_util import instantiate

        self = cls(server, station, users)
        await server.import_xml(str(NODESET))
        mv = await server.get_namespace_index(MACHINE_VISION)
        own = await server.register_namespace(NAMESPACE)
        await _define_id_subtypes(server, mv)

        async def mv_type(name: str):
            return await server.nodes.base_object_type.get_child(f"{mv}:{name}")

        async def state_machine_type(name: str):
            return await server.nodes.base_object_type.get_child(
                ["0:StateMachineType", "0:FiniteStateMachineType", f"{mv}:{name}"])

        vision_type = await mv_type("VisionSystemType")
        root = ua.NodeId(station.name, own)
        (vision, *_) = await instantiate(server.nodes.objects, vision_type, nodeid=root,
                                         bname=ua.QualifiedName(station.name, own), instantiate_optional=False)
        machine = await vision.get_child(f"{mv}:VisionStateMachine")
        machine_type = await state_machine_type("VisionStateMachineType")
        automatic_type = await state_machine_type("VisionAutomaticModeStateMachineType")
        await instantiate(machine, automatic_type, nodeid=ua.NodeId(f"{station.name}.VisionStateMachine."
                                                                    "AutomaticModeStateMachine", own),
                          bname=ua.QualifiedName("AutomaticModeStateMachine", mv), instantiate_optional=False)
        await copy_node(machine, await machine_type.get_child(f"{mv}:SelectModeAutomatic"),
                        nodeid=ua.NodeId(f"{station.name}.VisionStateMachine.SelectModeAutomatic", own))
        for name in ("ConfigurationManagement", "RecipeManagement", "ResultManagement"):
            await instantiate(vision, await mv_type(f"{name}Type"), nodeid=ua.NodeId(f"{station.name}.{name}", own),
                              bname=ua.QualifiedName(name, mv), instantiate_optional=False)
        automatic = await machine.get_child(f"{mv}:AutomaticModeStateMachine")
        self.nodes = {"vision": vision, "machine": machine, "automatic": automatic,
                      "state": await machine.get_child("0:CurrentState"),
                      "automatic_state": await automatic.get_child("0:CurrentState"),
                      "active_configuration": await vision.get_child([f"{mv}:ConfigurationManagement",
                                                                      f"{mv}:ActiveConfiguration"])}
        for state in ("Preoperational", "Halted", "Error", "Operational"):
            self.state_ids[state] = (await machine_type.get_child(f"{mv}:{state}")).nodeid
        for state in ("Initialized", "Ready", "SingleExecution", "ContinuousExecution"):
            self.state_ids[state] = (await automatic_type.get_child(f"{mv}:{state}")).nodeid

        await vision.set_event_notifier([ua.EventNotifier.SubscribeToEvents])
        await server.nodes.server.add_reference(vision.nodeid, ua.ObjectIds.HasNotifier)
        for event in ("ResultReady", "StateChanged", "JobStarted", "Ready", "AcquisitionDone", "RecipePrepared"):
            self.events[event] = await server.get_event_generator(await server.nodes.base_event_type.get_child(
                [f"{mv}:{event}EventType"] if event not in ("StateChanged",) else
                ["0:TransitionEventType", f"{mv}:StateChangedEventType"]), vision)
        self.events["Warning"] = await server.get_event_generator(ua.NodeId(1034, mv), vision)

        handlers = {"Halt": self.halt, "Reset": self.reset, "SelectModeAutomatic": self.select_mode_automatic,
                    "StartSingleJob": self.start_single_job, "StartContinuous": self.start_continuous,
                    "Stop": self.stop, "Abort": self.abort, "PrepareRecipe": self.prepare_recipe,
                    "UnprepareRecipe": self.unprepare_recipe, "GetRecipeListFiltered": self.get_recipe_list,
                    "ActivateConfiguration": self.activate_configuration,
                    "GetConfigurationById": self.get_configuration, "GetConfigurationList": self.get_configuration_list,
                    "GetResultById": self.get_result, "GetResultComponentsById": self.get_result_components,
                    "GetResultListFiltered": self.get_result_list}
        owners = {"Halt": machine, "Reset": machine, "SelectModeAutomatic": machine, "StartSingleJob": automatic,
                  "StartContinuous": automatic, "Stop": automatic, "Abort": automatic}
        for name, handler in handlers.items():
            owner = owners.get(name) or await vision.get_child(f"{mv}:{_MANAGER[name]}")
            method = await owner.get_child(f"{mv}:{name}")
            server.link_method(method, (await _Method.bind(method, name, handler, users, self.warn)).callback)
        return self

    async def start(self, in_flight: list[dict[str, Any]]) -> None:
        """The state after power-up: Preoperational, then into automatic mode (Initialized, and Ready when a
        recipe is prepared), following the scan jobs already queued or running."""
        await self._write_states()
        for state in in_flight:
            if _acquiring(state):
                self.acquiring[state["job_id"]] = state["job_id"]
        await self._transition("Operational", "Initialized", "PreoperationalToInitializedAuto")
        await self.refresh()

    async def refresh_forever(self) -> None:
        while True:
            await asyncio.sleep(REFRESH_S)
            try:
                await self.refresh()
            except Exception:  # the database may be down for a while; try again
                logger.exception("OPC UA: could not refresh the recipes and configurations")

    async def refresh(self) -> None:
        """Re-read the prepared recipe (the selected part type, which the HTTP API may change) and the active
        configuration."""
        from asyncua import ua

        async with self.recipe_lock:
            recipes, configurations = await asyncio.gather(asyncio.to_thread(self.station.recipes),
                                                           asyncio.to_thread(self.station.configurations))
            self.prepared = next((recipe for recipe in recipes if recipe.prepared), None)
        await self._settle()
        active = next((c for c in configurations if c.active), None)
        if active is not None:
            await self.nodes["active_configuration"].write_value(
                ua.Variant(_configuration_data(active), ua.VariantType.ExtensionObject))

    # following the scan jobs

    async def on_job_state(self, state: dict[str, Any]) -> None:
        job_id = state["job_id"]
        if state["status"] not in ("succeeded", "failed") and job_id not in self.results and state.get("scan_id"):
            # the result's rows (scan, recipe, configuration, the client's ids), read while the scan runs, so that
            # its ResultReady waits for no database round trip
            self.results[job_id] = asyncio.create_task(asyncio.to_thread(self.station.result, state["scan_id"]))
            if len(self.results) > _PREFETCHED:  # jobs whose end was never heard (the broker was away)
                self.results.pop(next(iter(self.results))).cancel()
        if _acquiring(state):
            if job_id not in self.acquiring:
                self.acquiring[job_id] = job_id
                if self.automatic_state == "Ready" and not self.starting:  # a scan another client (HTTP) started
                    await self._transition("Operational", "SingleExecution", "ReadyToSingleExecutionAuto")
                    await self._fire("JobStarted", JobId=ua_job(job_id))
            return
        opcua_job = self.acquiring.pop(job_id, None)
        if opcua_job is not None:
            self.last_job = opcua_job
        if opcua_job is not None and state["status"] != "failed":
            await self._fire("AcquisitionDone", JobId=ua_job(opcua_job))
        if state["status"] in ("succeeded", "failed") and state.get("scan_id"):
            result = await self._finished_result(state)
            if result is not None:
                await self._result_ready(result)
        if self.continuous is not None and self.continuous.get("scan_job") == job_id:
            if state["status"] == "succeeded":
                await self._continue()
            elif state["status"] == "failed":  # the station cannot scan (devices lost...): the run ends
                await self._end_continuous(f"scan job {job_id} failed: {state.get('error')}")
        await self._settle()

    async def _finished_result(self, state: dict[str, Any]) -> Result | None:
        """The result of a job that finished: the rows read while it ran with the job state's outcome, else read
        now."""
        read = self.results.pop(state["job_id"], None)
        try:
            result = await read if read is not None else None
        except Exception:  # the database was away then: read it now
            result = None
        if result is None:
            return await asyncio.to_thread(self.station.result, state["scan_id"])
        outcome = state.get("result") or {}
        return replace(result, status=state["status"], error=state.get("error"),
                       verdict=outcome.get("verdict") if state["status"] == "succeeded" else None,
                       features=outcome.get("features") if state["status"] == "succeeded" else None,
                       started_at=_timestamp(state.get("started_at")), finished_at=_timestamp(state.get("finished_at")),
                       stage_seconds=dict(outcome.get("stage_seconds") or {}))

    async def _settle(self) -> None:
        """The automatic transitions the station's state calls for."""
        if self.vision_state != "Operational":
            return
        if self.automatic_state == "SingleExecution" and not self.acquiring:
            await self._transition("Operational", "Ready", "SingleExecutionToReadyAuto")
            await self._fire("Ready", JobId=ua_job(self.last_job))
        if self.automatic_state == "Initialized" and self.prepared is not None:
            await self._transition("Operational", "Ready", "InitializedToReadyAuto")
        elif self.automatic_state == "Ready" and self.prepared is None:
            await self._transition("Operational", "Initialized", "ReadyToInitializedAuto")

    async def _result_ready(self, result: Result) -> None:
        data = _result_data(result)
        fields = {name: getattr(data, name) for name in (
            "ResultId", "IsPartial", "ResultState", "InternalRecipeId", "InternalConfigurationId", "JobId",
            "CreationTime", "MeasId", "PartId", "ExternalRecipeId", "ProductId", "ExternalConfigurationId",
            "ProcessingTimes", "ResultContent")}
        fields["IsSimulated"] = False
        verdict = result.verdict or ("not inspected" if result.status == "succeeded" else result.error)
        await self._fire("ResultReady", message=f"result {result.result_id}: {verdict}", **fields)

    async def _continue(self) -> None:
        """The next scan of the continuous run, or its end when the station cannot take it."""
        run = self.continuous
        try:
            job = await asyncio.to_thread(self.station.start_scan, part_id=run["part_id"], recipe=run["recipe"],
                                          meas_id=run["meas_id"], job_id=run["job_id"])
        except Exception as error:  # the station cannot go on (no calibration, queue full, database down)
            await self._end_continuous(str(error))
            return
        run["scan_job"] = job.id
        self.acquiring[job.id] = run["job_id"]

    async def _end_continuous(self, why: str) -> None:
        run, self.continuous = self.continuous, None
        logger.warning("OPC UA: the continuous job %s stops: %s", run["job_id"], why)
        if self.vision_state == "Operational" and self.automatic_state == "ContinuousExecution":
            await self._transition("Operational", "Ready", "ContinuousExecutionToReadyAuto")
            await self._fire("Ready", JobId=ua_job(run["job_id"]))

    # states and events

    async def _transition(self, vision_state: str, automatic_state: str | None, transition: str) -> None:
        before = self.automatic_state if self.vision_state == "Operational" else self.vision_state
        self.vision_state, self.automatic_state = vision_state, automatic_state
        after = automatic_state if vision_state == "Operational" else vision_state
        await self._write_states()
        if before != after:
            from asyncua import ua

            await self._fire("StateChanged", message=f"{before} -> {after}", Transition=ua.LocalizedText(transition),
                             FromState=ua.LocalizedText(before), ToState=ua.LocalizedText(after))

    async def _write_states(self) -> None:
        from asyncua import ua

        await _write_state(self.nodes["state"], self.vision_state, self.state_ids[self.vision_state])
        if self.vision_state == "Operational" and self.automatic_state is not None:
            await _write_state(self.nodes["automatic_state"], self.automatic_state,
                               self.state_ids[self.automatic_state])
        else:  # an inactive sub-state machine (OPC 40100-1, 8.1.2)
            await self.nodes["automatic_state"].write_value(
                ua.DataValue(StatusCode=ua.StatusCode(ua.StatusCodes.BadStateNotActive)))

    async def warn(self, message: str, status: str) -> None:
        """The message of a failed method call (OPC 40100-1, 11.5: at least a warning without acknowledgement,
        naming the method and its arguments), as a VisionWarningConditionType event."""
        from asyncua import ua

        try:
            await self._fire("Warning", message=message, ConditionName="MethodCallFailed",
                             Severity=ua.Variant(500, ua.VariantType.UInt16), Retain=False, BlockReaction=False,
                             StopReaction=False, ErrorString=status,
                             ConditionClassId=ua.Variant(ua.NodeId(ua.ObjectIds.BaseConditionClassType),
                                                         ua.VariantType.NodeId))
        except Exception:  # the call's answer must not depend on the message
            logger.exception("OPC UA: could not raise the warning %r", message)

    async def _fire(self, event: str, message: str | None = None, **fields: Any) -> None:
        from asyncua import ua

        generator = self.events[event]
        for name, value in fields.items():
            # the event type's properties declare no values, so the generator knows none of their types
            variant = value if isinstance(value, ua.Variant) else ua.Variant(value, _variant_type(value))
            setattr(generator.event, name, variant.Value)
            generator.event.data_types[name] = variant.VariantType
        await generator.trigger(time_attr=datetime.now(UTC), message=message or event)

    # the methods: each takes its input arguments by name and returns its outputs by name (Error is 0 unless
    # set); a failure raises MethodError

    def _require(self, *automatic_states: str, vision_states: tuple[str, ...] = ()) -> None:
        if self.vision_state in vision_states:
            return
        if self.vision_state == "Operational" and self.automatic_state in automatic_states:
            return
        now = self.automatic_state if self.vision_state == "Operational" else self.vision_state
        raise MethodError(_status("BadInvalidState"), f"not possible in state {now}")

    async def halt(self, Cause: int, CauseDescription: str | None) -> dict[str, Any]:
        self.continuous = None
        if self.vision_state != "Halted":
            await self._transition("Halted", None, f"{self.vision_state}ToHalted")
        return {}

    async def reset(self, Cause: int, CauseDescription: str | None) -> dict[str, Any]:
        self.continuous = None
        if self.vision_state != "Preoperational":
            await self._transition("Preoperational", None, f"{self.vision_state}ToPreoperational")
        return {}

    async def select_mode_automatic(self) -> dict[str, Any]:
        self._require(vision_states=("Preoperational",))
        await self._transition("Operational", "Initialized", "PreoperationalToInitialized")
        await self.refresh()
        return {}

    async def start_single_job(self, MeasId, PartId, RecipeId, ProductId, Parameters) -> dict[str, Any]:
        self._require("Ready")
        recipe = await self._job_recipe(RecipeId, ProductId)
        job = await self._start_scan(_text(PartId), recipe, _text(MeasId), None)
        self.acquiring[job.id] = job.id
        await self._transition("Operational", "SingleExecution", "ReadyToSingleExecution")
        await self._fire("JobStarted", JobId=ua_job(job.id))
        return {"JobId": ua_job(job.id)}

    async def start_continuous(self, MeasId, PartId, RecipeId, ProductId, Parameters) -> dict[str, Any]:
        from services.db.models import new_id

        self._require("Ready")
        recipe = await self._job_recipe(RecipeId, ProductId)
        run = {"job_id": new_id(), "part_id": _text(PartId), "recipe": recipe, "meas_id": _text(MeasId)}
        job = await self._start_scan(run["part_id"], recipe, run["meas_id"], run["job_id"])
        run["scan_job"] = job.id
        self.continuous = run
        self.acquiring[job.id] = run["job_id"]
        await self._transition("Operational", "ContinuousExecution", "ReadyToContinuousExecution")
        await self._fire("JobStarted", JobId=ua_job(run["job_id"]))
        return {"JobId": ua_job(run["job_id"])}

    async def stop(self, Cause: int, CauseDescription: str | None) -> dict[str, Any]:
        """No more scans; the one running finishes and keeps its result (Stop and Abort are always
        executable: outside an execution they change nothing)."""
        await self._end_execution("Stop", abort=False)
        return {}

    async def abort(self, Cause: int, CauseDescription: str | None) -> dict[str, Any]:
        """No more scans, and those still queued are cancelled (their results: Aborted); a scan already
        capturing cannot be interrupted and keeps its result."""
        await self._end_execution("Abort", abort=True)
        return {}

    async def _end_execution(self, cause: str, abort: bool) -> None:
        if self.vision_state != "Operational" or self.automatic_state not in ("SingleExecution",
                                                                               "ContinuousExecution"):
            return
        run, self.continuous = self.continuous, None
        job_id = run["job_id"] if run else next(iter(self.acquiring.values()), "")
        if abort:
            for cancelled in await asyncio.to_thread(self.station.abort_queued, set(self.acquiring)):
                self.acquiring.pop(cancelled, None)
        await self._transition("Operational", "Ready", f"{self.automatic_state}ToReady{cause}")
        await self._fire("Ready", JobId=ua_job(job_id))

    async def prepare_recipe(self, ExternalId, InternalIdIn) -> dict[str, Any]:
        self._require("Initialized", "Ready")
        recipe = await self._recipe(ExternalId, InternalIdIn)
        async with self.recipe_lock:
            await asyncio.to_thread(self.station.prepare, recipe)
            self.prepared = replace(recipe, prepared=True)
        await self._fire("RecipePrepared", ExternalId=_external_recipe(recipe), InternalId=_internal_recipe(recipe),
                         ProductId=None)
        if self.automatic_state == "Initialized":
            await self._transition("Operational", "Ready", "InitializedToReadyRecipe")
        return {"InternalIdOut": _internal_recipe(recipe), "IsCompleted": True}

    async def unprepare_recipe(self, ExternalId, InternalIdIn) -> dict[str, Any]:
        self._require("Initialized", "Ready")
        recipe = await self._recipe(ExternalId, InternalIdIn)
        if recipe.prepared:
            async with self.recipe_lock:
                await asyncio.to_thread(self.station.unprepare, recipe)
                self.prepared = None
            if self.automatic_state == "Ready":
                await self._transition("Operational", "Initialized", "ReadyToInitializedRecipe")
        return {"InternalIdOut": _internal_recipe(recipe)}

    async def get_recipe_list(self, ExternalId, ProductId, IsPrepared, MaxResults, StartIndex, Timeout):
        recipes = await asyncio.to_thread(self.station.recipes)
        external, product = _text(ExternalId), _text(ProductId)
        if IsPrepared not in (0, 1, 2):
            raise _bad_argument(2, "IsPrepared: not a TriStateBooleanDataType (0 false, 1 true, 2 don't care)")
        chosen = [recipe for recipe in recipes if (not external or recipe.external_id == external)
                  and (not product or recipe.external_id == product)
                  and (IsPrepared == 2 or recipe.prepared == bool(IsPrepared))]
        page, complete = _page(chosen, MaxResults, StartIndex)
        return {"IsComplete": complete, "ResultCount": len(page), "RecipeHandle": 0,
                "RecipeList": [_internal_recipe(recipe) for recipe in page]}

    async def activate_configuration(self, InternalId) -> dict[str, Any]:
        self._require("Initialized", "Ready", vision_states=("Preoperational",))
        configuration = await asyncio.to_thread(self.station.find_configuration, _text(InternalId))
        if configuration is None:
            raise _bad_argument(0, f"there is no configuration {_text(InternalId)!r} of station "
                                   f"{self.station.name!r}", "BadNotFound")
        if not configuration.has_rig:
            raise _bad_argument(0, f"configuration {configuration.internal_id} has no rig yet")
        await asyncio.to_thread(self.station.activate, configuration)
        await self.refresh()
        return {}

    async def get_configuration(self, InternalId, Timeout) -> dict[str, Any]:
        configuration = await asyncio.to_thread(self.station.find_configuration, _text(InternalId))
        if configuration is None:
            raise _bad_argument(0, f"there is no configuration {_text(InternalId)!r}", "BadNotFound")
        return {"ConfigurationHandle": 0, "Configuration": _configuration_data(configuration)}

    async def get_configuration_list(self, MaxResults, StartIndex, Timeout) -> dict[str, Any]:
        configurations = await asyncio.to_thread(self.station.configurations)
        page, complete = _page(configurations, MaxResults, StartIndex)
        return {"IsComplete": complete, "ResultCount": len(page), "ConfigurationHandle": 0,
                "ConfigurationList": [_configuration_data(c) for c in page]}

    async def get_result(self, ResultId, Timeout) -> dict[str, Any]:
        result = await self._wait_for_result(_text(ResultId), Timeout)
        return {"ResultHandle": 0, "Result": _result_data(result)}

    async def get_result_components(self, ResultId, Timeout) -> dict[str, Any]:
        data = _result_data(await self._wait_for_result(_text(ResultId), Timeout))
        return {name: getattr(data, name) for name in (
            "IsPartial", "IsSimulated", "ResultState", "MeasId", "PartId", "ExternalRecipeId", "InternalRecipeId",
            "ProductId", "ExternalConfigurationId", "InternalConfigurationId", "JobId", "CreationTime",
            "ProcessingTimes", "ResultContent")} | {"HasTransferableDataOnFile": False, "ResultHandle": 0}

    async def get_result_list(self, ResultState, MeasId, PartId, ExternalRecipeId, InternalRecipeId,
                              ExternalConfigurationId, InternalConfigurationId, ProductId, JobId, MaxResults,
                              StartIndex, Timeout) -> dict[str, Any]:
        where = ResultFilter(ResultState or None, *(_text(value) or None for value in (
            MeasId, PartId, ExternalRecipeId, InternalRecipeId, ExternalConfigurationId, InternalConfigurationId,
            ProductId, JobId)))
        results = await asyncio.to_thread(self.station.results, where)
        page, complete = _page(results, MaxResults, StartIndex)
        return {"IsComplete": complete, "ResultCount": len(page), "ResultHandle": 0,
                "ResultList": [_result_data(result) for result in page]}

    async def _wait_for_result(self, result_id: str, timeout_ms: int) -> Result:
        loop = asyncio.get_running_loop()
        until = loop.time() + min(max(timeout_ms, 0), MAX_WAIT_MS) / 1000
        while True:
            result = await asyncio.to_thread(self.station.result, result_id)
            if result is None:
                raise _bad_argument(0, f"there is no result {result_id!r} of station {self.station.name!r}",
                                    "BadNotFound")
            if result.finished or loop.time() >= until:
                return result
            await asyncio.sleep(0.1)

    async def _recipe(self, external, internal) -> Recipe:
        recipe = await asyncio.to_thread(self.station.find_recipe, _text(internal), _text(external))
        if recipe is None:
            which = 1 if _text(internal) else 0
            raise _bad_argument(which, f"there is no recipe {_text(internal) or _text(external)!r} of station "
                                       f"{self.station.name!r}", "BadNotFound")
        return recipe

    async def _job_recipe(self, recipe_id, product_id) -> Recipe | None:
        """The recipe a job runs: the prepared one, which a non-empty RecipeId or ProductId must name."""
        for index, wanted in ((2, _text(recipe_id)), (3, _text(product_id))):
            if wanted and (self.prepared is None or wanted != self.prepared.external_id):
                raise _bad_argument(index, f"{wanted!r} is not the prepared recipe"
                                           f" ({self.prepared.external_id if self.prepared else 'none is'})",
                                    "BadNotFound")
        return self.prepared

    async def _start_scan(self, part_id: str, recipe: Recipe | None, meas_id: str, job_id: str | None):
        self.starting += 1
        try:
            return await asyncio.to_thread(self.station.start_scan, part_id=part_id or None, recipe=recipe,
                                           meas_id=meas_id, job_id=job_id)
        except JobRefused as refused:
            status = {"queue-full": "BadResourceUnavailable", "no-active-calibration": "BadInvalidState"}
            raise MethodError(_status(status.get(refused.kind, "BadInvalidArgument")), str(refused)) from None
        finally:
            self.starting -= 1


_MANAGER = {name: manager for manager, names in (
    ("RecipeManagement", ("PrepareRecipe", "UnprepareRecipe", "GetRecipeListFiltered")),
    ("ConfigurationManagement", ("ActivateConfiguration", "GetConfigurationById", "GetConfigurationList")),
    ("ResultManagement", ("GetResultById", "GetResultComponentsById", "GetResultListFiltered"))) for name in names}


class _Method:
    """A method's callback: the caller's scope checked, its input arguments checked against the method's
    InputArguments (count, type, length), the handler called with them by name, and its outputs typed after
    the OutputArguments. Failures answer with status codes (OPC 10000-4, Call service) and change nothing."""

    def __init__(self, name: str, handler, users: ApiKeyUsers, inputs: list, outputs: list, warn) -> None:
        self.name, self.handler, self.users, self.inputs, self.outputs = name, handler, users, inputs, outputs
        self.warn = warn

    @classmethod
    async def bind(cls, method, name: str, handler, users: ApiKeyUsers, warn):
        arguments = {}
        for prop in ("InputArguments", "OutputArguments"):
            try:
                arguments[prop] = await (await method.get_child(f"0:{prop}")).read_value()
            except Exception:  # SelectModeAutomatic has no input arguments
                arguments[prop] = []
        return cls(name, handler, users, arguments["InputArguments"], arguments["OutputArguments"], warn)

    async def callback(self, parent, *variants):
        """What asyncua calls (a coroutine function, awaited in the caller's connection task)."""
        from asyncua import ua

        result = ua.CallMethodResult()
        try:
            if not self.users.may_call(caller(), self.name):
                raise MethodError(_status("BadUserAccessDenied"), f"the API key lacks the "
                                                                  f"'{METHOD_SCOPES[self.name]}' scope")
            values = self._check(variants)
            outputs = await self.handler(**values)
            result.OutputArguments = [_output(argument, outputs.get(argument.Name, 0 if argument.Name == "Error"
                                                                     else None)) for argument in self.outputs]
            result.StatusCode = ua.StatusCode(ua.StatusCodes.Good)
        except MethodError as error:
            message = f"{self.name}({_describe(variants)}) failed: {error}"
            logger.warning("OPC UA: %s", message)
            await self.warn(message, ua.StatusCode(error.status).name)
            result.StatusCode = ua.StatusCode(error.status)
            result.InputArgumentResults = [ua.StatusCode(error.argument_results.get(i, ua.StatusCodes.Good))
                                           for i in range(len(variants))] if error.argument_results else []
        except Exception:
            logger.exception("OPC UA: %s failed", self.name)
            result.StatusCode = ua.StatusCode(ua.StatusCodes.BadInternalError)
        return result

    def _check(self, variants) -> dict[str, Any]:
        from asyncua import ua

        if len(variants) < len(self.inputs):
            raise MethodError(_status("BadArgumentsMissing"), f"{self.name} takes {len(self.inputs)} arguments")
        if len(variants) > len(self.inputs):
            raise MethodError(_status("BadTooManyArguments"), f"{self.name} takes {len(self.inputs)} arguments")
        values, bad = {}, {}
        for index, (argument, variant) in enumerate(zip(self.inputs, variants)):
            try:
                values[argument.Name] = _input(argument, variant)
            except ValueError as error:
                bad[index] = ua.StatusCodes.BadTypeMismatch if "type" in str(error) else ua.StatusCodes.BadOutOfRange
                logger.info("OPC UA: %s: %s: %s", self.name, argument.Name, error)
        if bad:
            raise MethodError(_status("BadInvalidArgument"), f"{self.name}: bad arguments", bad)
        return values


def _input(argument, variant) -> Any:
    """The value of an input argument, checked against its declared DataType (ValueError: wrong type or out of
    range)."""
    from asyncua import ua

    data_type, value = argument.DataType, variant.Value
    kind = variant.VariantType
    if argument.ValueRank == 1:  # BaseDataType[] Parameters: thermofield's recipes take none
        if value in (None, []):
            return []
        raise ValueError("out of range: the station's recipes take no parameters")
    expected = _builtin(data_type)
    if expected is not None:
        if kind != expected and not (kind == ua.VariantType.Null and expected == ua.VariantType.String):
            raise ValueError(f"type {kind.name}, not {expected.name}")
        if isinstance(value, str):
            _check_text(value)
        return value
    cls = ua.extension_objects_by_datatype.get(data_type)
    if value is None:
        return None
    if cls is None or not isinstance(value, cls):
        raise ValueError(f"type {type(value).__name__}, not {getattr(cls, '__name__', data_type)}")
    _check_text(getattr(value, "Id", "") or "")
    return value


def _check_text(text: str) -> None:
    if len(text) > MAX_TEXT:
        raise ValueError(f"out of range: longer than {MAX_TEXT} characters")
    if any(ord(character) < 32 and character not in "\t\n\r" for character in text):
        raise ValueError("out of range: a control character")


def _output(argument, value) -> Any:
    from asyncua import ua

    if argument.ValueRank == 1:
        if _builtin(argument.DataType) is None and argument.DataType != ua.NodeId(ua.ObjectIds.BaseDataType):
            return ua.Variant(list(value or []), ua.VariantType.ExtensionObject)
        return ua.Variant(list(value or []), ua.VariantType.Variant)
    expected = _builtin(argument.DataType)
    if expected is None:
        return ua.Variant(value, ua.VariantType.ExtensionObject)
    return ua.Variant(value, expected)


def _builtin(data_type) -> Any:
    """The built-in Variant type of a DataType the methods use, None for a structure."""
    from asyncua import ua

    builtins = {ua.ObjectIds.Int32: ua.VariantType.Int32, ua.ObjectIds.UInt32: ua.VariantType.UInt32,
                ua.ObjectIds.String: ua.VariantType.String, ua.ObjectIds.Boolean: ua.VariantType.Boolean,
                ua.ObjectIds.UtcTime: ua.VariantType.DateTime, ua.ObjectIds.DateTime: ua.VariantType.DateTime}
    if data_type.NamespaceIndex == 0:
        return builtins.get(data_type.Identifier)
    # the Machine Vision namespace's subtypes of built-in types and its enumeration
    return {3009: ua.VariantType.Int32, 3018: ua.VariantType.UInt32, 3014: ua.VariantType.Int32,
            3017: ua.VariantType.String}.get(data_type.Identifier)


def _variant_type(value: Any):
    from asyncua import ua

    if isinstance(value, bool):
        return ua.VariantType.Boolean
    if isinstance(value, int):
        return ua.VariantType.Int32
    if isinstance(value, str):
        return ua.VariantType.String
    if isinstance(value, datetime):
        return ua.VariantType.DateTime
    if isinstance(value, ua.LocalizedText):
        return ua.VariantType.LocalizedText
    if isinstance(value, list):
        return ua.VariantType.Variant
    return ua.VariantType.Null if value is None else ua.VariantType.ExtensionObject


def _page(items: list, max_results: int, start_index: int) -> tuple[list, bool]:
    limit = MAX_RESULTS if not max_results else min(max_results, MAX_RESULTS)
    page = items[start_index:start_index + limit]
    return page, start_index + len(page) >= len(items)


def _bad_argument(index: int, message: str, status: str = "BadInvalidArgument") -> MethodError:
    return MethodError(_status("BadInvalidArgument"), message, {index: _status(status)})


def _status(name: str) -> int:
    from asyncua import ua

    return getattr(ua.StatusCodes, name)


def _text(value) -> str:
    """An id argument's text: a string, or the Id of an id structure; empty for none."""
    if value is None:
        return ""
    if isinstance(value, str):
        return value.strip()
    return (getattr(value, "Id", "") or "").strip()


def _describe(variants) -> str:
    return ", ".join(repr(getattr(variant, "Value", variant))[:80] for variant in variants)


def _timestamp(text: str | None) -> datetime | None:
    return None if text is None else datetime.fromisoformat(text)


def _acquiring(state: dict[str, Any]) -> bool:
    return state["status"] == "queued" or (state["status"] == "running" and state.get("stage") in _ACQUIRING_STAGES)


def ua_job(job_id: str):
    from asyncua import ua

    return ua.JobIdDataType(Id=job_id)


def _internal_recipe(recipe: Recipe):
    from asyncua import ua

    return ua.RecipeIdInternalDataType(Id=recipe.internal_id, Description=ua.LocalizedText(
        f"{recipe.external_id} ({recipe.material})"))


def _external_recipe(recipe: Recipe):
    from asyncua import ua

    return ua.RecipeIdExternalDataType(Id=recipe.external_id)


def _configuration_data(configuration: Configuration):
    from asyncua import ua

    return ua.ConfigurationDataType(
        HasTransferableDataOnFile=False, ExternalId=ua.ConfigurationIdDataType(Id=configuration.external_id),
        InternalId=ua.ConfigurationIdDataType(Id=configuration.internal_id), LastModified=configuration.created_at)


def _result_data(result: Result):
    """A scan as OPC 40100-1's ResultDataType; its verdict (``OK``, ``NotOK``, ``NotDecidable`` or empty when not
    inspected) and features (JSON) are the ResultContent."""
    import json

    from asyncua import ua

    recipe = result.recipe
    seconds = result.stage_seconds
    capture_ms = 1000 * seconds.get("capture", 0.0)
    times = None
    if result.started_at is not None and result.finished_at is not None:
        total_ms = 1000 * (result.finished_at - result.started_at).total_seconds()
        times = ua.ProcessingTimesDataType(StartTime=result.started_at, EndTime=result.finished_at,
                                           AcquisitionDuration=capture_ms,
                                           ProcessingDuration=max(total_ms - capture_ms, 0.0))
    content = [ua.Variant(result.verdict or "", ua.VariantType.String),
               ua.Variant(json.dumps(result.features or []), ua.VariantType.String)]
    return ua.ResultDataType(
        ResultId=ua.ResultIdDataType(Id=result.result_id), HasTransferableDataOnFile=False, IsPartial=False,
        IsSimulated=False, ResultState=result_state(result),
        MeasId=ua.MeasIdDataType(Id=result.meas_id), PartId=ua.PartIdDataType(Id=result.part_id),
        ExternalRecipeId=None if recipe is None else _external_recipe(recipe),
        InternalRecipeId=ua.RecipeIdInternalDataType(Id="") if recipe is None else _internal_recipe(recipe),
        ProductId=None if recipe is None else ua.ProductIdDataType(Id=recipe.external_id),
        ExternalConfigurationId=ua.ConfigurationIdDataType(Id=result.configuration_name),
        InternalConfigurationId=ua.ConfigurationIdDataType(Id=result.configuration_id),
        JobId=ua.JobIdDataType(Id=result.job_id), CreationTime=result.finished_at or result.created_at,
        ProcessingTimes=times, ResultContent=content)


async def _write_state(node, name: str, state_id) -> None:
    from asyncua import ua

    await node.write_value(ua.LocalizedText(name))
    await (await node.get_child("0:Id")).write_value(ua.Variant(state_id, ua.VariantType.NodeId))


async def _define_id_subtypes(server, mv: int) -> None:
    """Give RecipeIdExternalDataType, RecipeIdInternalDataType and ConfigurationIdDataType the DataTypeDefinition
    the NodeSet leaves out (they add no field to BinaryIdBaseDataType), each with its own encoding, so that
    asyncua encodes them as themselves rather than as their abstract base (and clients read the definition)."""
    from asyncua import ua

    base = await server.get_node(ua.NodeId(3019, mv)).read_data_type_definition()
    for identifier, encoding, name in ((3002, 5002, "RecipeIdExternalDataType"),
                                       (3013, 5268, "RecipeIdInternalDataType"),
                                       (3008, 5090, "ConfigurationIdDataType")):
        if hasattr(ua, name) and getattr(ua, name).data_type != ua.NodeId(identifier, mv):
            delattr(ua, name)  # an earlier server's alias of the base type, in the way of the subtype's own class
        definition = ua.StructureDefinition(DefaultEncodingId=ua.NodeId(encoding, mv),
                                            BaseDataType=ua.NodeId(3019, mv), StructureType=base.StructureType,
                                            Fields=base.Fields)
        await server.write_attribute_value(ua.NodeId(identifier, mv), ua.DataValue(ua.Variant(definition)),
                                           ua.AttributeIds.DataTypeDefinition)
    await server.load_data_type_definitions()
