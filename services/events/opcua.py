"""An OPC UA server (asyncua) publishing the station's scans after OPC 40100-1 (Machine Vision) where it applies.

Address space (namespace ``urn:thermofield:machine-vision``; browse names follow OPC 40100-1, but the types
are thermofield's own: the companion specification's nodeset is not loaded)::

    Objects/VisionSystem                                 VisionSystemType, event notifier
        VisionStateMachine/CurrentState                  "Preoperational" while starting, then "Operational"
        VisionStateMachine/AutomaticModeStateMachine/CurrentState
                                                         "Ready", or "SingleExecution" while a scan runs
        RecipeManagement/Recipes/<part type name>        one recipe per part type of the station:
            InternalRecipeId, ProductId, Material, Prepared (the station's selected part type)
        ResultManagement/LastResult                      the latest result: ResultId, PartId, ResultState,
                                                         Verdict, JobId, InternalRecipeId, CreationTime

Every finished scan job fires a ``ResultReadyEventType`` event from ``VisionSystem`` with ``ResultId``
(the scan id), ``PartId`` (the MES's part id), ``ResultState``, ``Verdict`` (``OK``, ``NotOK``,
``NotDecidable`` or empty), ``IsPartial`` (false), ``JobId``, ``InternalRecipeId`` (the part type id),
``ProductId`` (the part type's name) and ``CreationTime``. ``ResultState`` carries the ResultEvaluation
codes of OPC 40001-101: 1 OK, 2 NotOK, 3 NotDecidable, 0 no verdict (the scan had no part type, or its
job failed; the event's Message says which).

The server runs its own asyncio loop in a thread of the process whose job tracker records the scans
(``thermofield serve``); :meth:`OpcUaServer.notify` is the tracker's listener. Recipes are re-read from
the database every ``RECIPE_REFRESH_S`` seconds, so part types uploaded through any API process appear.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from datetime import UTC, datetime
from typing import Any
from urllib.parse import urlsplit

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from services.db.models import PartType, Scan
from services.errors import InputError

logger = logging.getLogger(__name__)

NAMESPACE = "urn:thermofield:machine-vision"
RECIPE_REFRESH_S = 2.0
RESULT_STATES = {"OK": 1, "NotOK": 2, "NotDecidable": 3}
_START_TIMEOUT_S = 30.0
_EVENT_PROPERTIES = (("ResultId", "String"), ("PartId", "String"), ("ResultState", "Int32"), ("Verdict", "String"),
                     ("IsPartial", "Boolean"), ("JobId", "String"), ("InternalRecipeId", "String"),
                     ("ProductId", "String"), ("CreationTime", "DateTime"))


def result_state(verdict: str | None) -> int:
    """The ResultEvaluation code of OPC 40001-101 for a verdict (0: none)."""
    return RESULT_STATES.get(verdict or "", 0)


class OpcUaServer:
    """The station's OPC UA server at ``endpoint`` (``opc.tcp://host:port/path``), started as a context manager.

    Parameters
    ----------
    endpoint : str
        Where clients connect; the server binds the URL's host and port.
    sessions : sessionmaker
        The service database (part types, scans).
    station : str
        The station whose part types are its recipes.
    """

    def __init__(self, endpoint: str, sessions: sessionmaker[Session], station: str) -> None:
        address = urlsplit(endpoint)
        if address.scheme != "opc.tcp" or not address.hostname or address.port is None:
            raise InputError(f"THERMOFIELD_OPCUA_ENDPOINT: {endpoint!r} is not an opc.tcp://host:port/... URL")
        self.endpoint = endpoint
        self.sessions = sessions
        self.station = station
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
        if self._error is not None:
            raise InputError(f"the OPC UA server cannot listen at {self.endpoint} ({self._error}); "
                             "is the port taken? set THERMOFIELD_OPCUA_ENDPOINT") from None
        return self

    def __exit__(self, *exc_info: object) -> None:
        if self._loop is not None and self._thread.is_alive():
            self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(timeout=10)

    def notify(self, state: dict[str, Any]) -> None:
        """Take a job state the tracker announced (thread-safe, never blocks); scan jobs move the state machine
        and, finished, fire ResultReady."""
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

        self._loop = asyncio.get_running_loop()
        self._states, self._stop = asyncio.Queue(), asyncio.Event()
        server = Server()
        await server.init()
        server.set_endpoint(self.endpoint)
        server.set_server_name(f"thermofield {self.station}")
        server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
        nodes = await _build_address_space(server, await server.register_namespace(NAMESPACE))
        async with server:
            await nodes.state.write_value(ua.LocalizedText("Operational"))
            self._started.set()
            refresh = asyncio.create_task(self._refresh_recipes(nodes))
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
                        await self._on_state(nodes, getter.result())
                    except Exception:  # a bad state must not stop the server
                        logger.exception("OPC UA: could not publish a scan's state")
            finally:
                refresh.cancel()

    async def _on_state(self, nodes: _Nodes, state: dict[str, Any]) -> None:
        from asyncua import ua

        running = state["status"] == "running"
        await nodes.automatic.write_value(ua.LocalizedText("SingleExecution" if running else "Ready"))
        if state["status"] not in ("succeeded", "failed") or not state.get("scan_id"):
            return
        scan = await asyncio.to_thread(self._scan, state["scan_id"])
        verdict = scan["verdict"] if state["status"] == "succeeded" else None
        if state["status"] == "failed":
            message = f"scan {state['scan_id']} failed: {state.get('error')}"
        elif verdict is None:
            message = f"scan {state['scan_id']} done, not inspected (no part type)"
        else:
            message = f"scan {state['scan_id']}: {verdict}"
        values = {"ResultId": state["scan_id"], "PartId": scan["part_id"] or "", "ResultState": result_state(verdict),
                  "Verdict": verdict or "", "IsPartial": False, "JobId": state["job_id"],
                  "InternalRecipeId": scan["part_type_id"] or "", "ProductId": scan["part_type_name"] or "",
                  "CreationTime": datetime.now(UTC)}
        for name, kind in _EVENT_PROPERTIES:
            if name != "IsPartial":
                await nodes.last_result[name].write_value(ua.Variant(values[name], getattr(ua.VariantType, kind)))
            setattr(nodes.events.event, name, values[name])  # typed by the event type's property
        await nodes.events.trigger(message=message)

    def _scan(self, scan_id: str) -> dict[str, Any]:
        with self.sessions() as session:
            scan = session.get(Scan, scan_id)
            part_type = session.get(PartType, scan.part_type_id) if scan and scan.part_type_id else None
            return {"verdict": scan.verdict if scan else None, "part_id": scan.part_id if scan else None,
                    "part_type_id": part_type.id if part_type else None,
                    "part_type_name": part_type.name if part_type else None}

    def _part_types(self) -> list[tuple[str, str, str, bool]]:
        with self.sessions() as session:
            rows = session.scalars(select(PartType).where(PartType.station == self.station)
                                   .order_by(PartType.created_at))
            return [(row.id, row.name, row.material, row.selected) for row in rows]

    async def _refresh_recipes(self, nodes: _Nodes) -> None:
        """Keep ``RecipeManagement/Recipes`` equal to the station's part types."""
        from asyncua import ua

        while True:
            try:
                part_types = await asyncio.to_thread(self._part_types)
                present = {part_type_id for part_type_id, *_ in part_types}
                for part_type_id in set(nodes.recipes) - present:
                    await nodes.recipes.pop(part_type_id)[0].delete()
                for part_type_id, name, material, selected in part_types:
                    if part_type_id not in nodes.recipes:
                        recipe = await nodes.recipe_folder.add_object(
                            ua.NodeId(f"Recipe.{part_type_id}", nodes.namespace), ua.QualifiedName(name, nodes.namespace))
                        for prop, value in (("InternalRecipeId", part_type_id), ("ProductId", name),
                                            ("Material", material)):
                            await recipe.add_property(nodes.namespace, prop, value)
                        prepared = await recipe.add_property(nodes.namespace, "Prepared", selected)
                        nodes.recipes[part_type_id] = (recipe, prepared)
                    await nodes.recipes[part_type_id][1].write_value(selected)
            except Exception:  # the database may be down for a while; try again
                logger.exception("OPC UA: could not refresh the recipes")
            await asyncio.sleep(RECIPE_REFRESH_S)


class _Nodes:
    """The nodes the server writes."""

    def __init__(self, namespace: int) -> None:
        self.namespace = namespace
        self.state = self.automatic = self.recipe_folder = self.events = None
        self.last_result: dict[str, Any] = {}
        self.recipes: dict[str, tuple[Any, Any]] = {}


async def _build_address_space(server, namespace: int) -> _Nodes:
    from asyncua import ua

    nodes = _Nodes(namespace)
    vision_type = await server.nodes.base_object_type.add_object_type(namespace, "VisionSystemType")
    event_type = await server.create_custom_event_type(
        namespace, "ResultReadyEventType", ua.ObjectIds.BaseEventType,
        [(name, getattr(ua.VariantType, kind)) for name, kind in _EVENT_PROPERTIES])
    vision = await server.nodes.objects.add_object(ua.NodeId("VisionSystem", namespace),
                                                   ua.QualifiedName("VisionSystem", namespace), vision_type.nodeid)
    await vision.set_event_notifier([ua.EventNotifier.SubscribeToEvents])
    await server.nodes.server.add_reference(vision.nodeid, ua.ObjectIds.HasNotifier)
    machine = await vision.add_object(namespace, "VisionStateMachine")
    nodes.state = await machine.add_variable(ua.NodeId("VisionStateMachine.CurrentState", namespace),
                                             ua.QualifiedName("CurrentState", namespace),
                                             ua.LocalizedText("Preoperational"))
    automatic = await machine.add_object(namespace, "AutomaticModeStateMachine")
    nodes.automatic = await automatic.add_variable(
        ua.NodeId("AutomaticModeStateMachine.CurrentState", namespace), ua.QualifiedName("CurrentState", namespace),
        ua.LocalizedText("Ready"))
    recipes = await vision.add_object(namespace, "RecipeManagement")
    nodes.recipe_folder = await recipes.add_folder(ua.NodeId("Recipes", namespace),
                                                   ua.QualifiedName("Recipes", namespace))
    results = await vision.add_object(namespace, "ResultManagement")
    last = await results.add_object(ua.NodeId("LastResult", namespace), ua.QualifiedName("LastResult", namespace))
    for name, kind in _EVENT_PROPERTIES:
        if name != "IsPartial":
            nodes.last_result[name] = await last.add_variable(
                ua.NodeId(f"LastResult.{name}", namespace), ua.QualifiedName(name, namespace),
                ua.get_default_value(getattr(ua.VariantType, kind)), varianttype=getattr(ua.VariantType, kind))
    nodes.events = await server.get_event_generator(event_type, vision)
    return nodes
