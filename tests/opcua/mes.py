"""An MES as the tests and the benchmark play it: an asyncua client that connects signed and encrypted with its
own application certificate (trusted by copying it into the server's trusted/ directory, as docs/opcua.md says),
logs in with an API key as its password, finds the station's VisionSystem by its type (OPC 40100-1) and calls
its methods by name."""

from __future__ import annotations

import asyncio
import shutil
import time
from pathlib import Path
from typing import Any

from asyncua import Client, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from cryptography.x509.oid import ExtendedKeyUsageOID

MACHINE_VISION = "http://opcfoundation.org/UA/MachineVision"
CLIENT_URI = "urn:thermofield:test:mes"
METHOD_PLACES = {
    "Halt": ("VisionStateMachine",), "Reset": ("VisionStateMachine",),
    "SelectModeAutomatic": ("VisionStateMachine",),
    **{name: ("VisionStateMachine", "AutomaticModeStateMachine")
       for name in ("StartSingleJob", "StartContinuous", "Stop", "Abort")},
    **{name: ("RecipeManagement",) for name in ("PrepareRecipe", "UnprepareRecipe", "GetRecipeListFiltered")},
    **{name: ("ConfigurationManagement",)
       for name in ("ActivateConfiguration", "GetConfigurationById", "GetConfigurationList")},
    **{name: ("ResultManagement",) for name in ("GetResultById", "GetResultComponentsById", "GetResultListFiltered")},
}
"""Where each of the Basic Vision System Server profile's mandatory methods is, below the VisionSystem."""


async def client_certificate(directory: Path, trusted_dir: Path | None) -> tuple[Path, Path]:
    """The MES's certificate and key (made once in ``directory``), copied into the server's ``trusted_dir``."""
    directory.mkdir(parents=True, exist_ok=True)
    certificate, key = directory / "mes-certificate.der", directory / "mes-key.pem"
    await setup_self_signed_certificate(key, certificate, CLIENT_URI, "localhost",
                                        [ExtendedKeyUsageOID.CLIENT_AUTH], {"commonName": "test MES"})
    if trusted_dir is not None:
        trusted_dir.mkdir(parents=True, exist_ok=True)
        shutil.copy(certificate, trusted_dir / certificate.name)
    return certificate, key


class Mes:
    """A connected MES client (``async with Mes(...) as mes``); ``events`` collects the VisionSystem's events."""

    def __init__(self, endpoint: str, api_key: str, certificate: tuple[Path, Path] | None = None,
                 timeout_s: float = 30.0, watchdog_s: float = 10.0) -> None:
        # asyncua probes the server every watchdog interval and gives up after as long (1 s by default): a server
        # whose process is busy scanning on a loaded machine may take longer to answer
        self.client = Client(endpoint, timeout=timeout_s, watchdog_intervall=watchdog_s)
        self.client.application_uri = CLIENT_URI
        self.client.set_user("mes")
        self.client.set_password(api_key)
        self.certificate = certificate
        self.events: list[dict[str, Any]] = []
        self.status_changes: list[Any] = []
        self.event_times: list[float] = []
        self.mv = 0
        self.vision = None

    async def __aenter__(self) -> Mes:
        if self.certificate is not None:
            await self.client.set_security(SecurityPolicyBasic256Sha256, str(self.certificate[0]),
                                           str(self.certificate[1]), mode=ua.MessageSecurityMode.SignAndEncrypt)
        await self.client.connect()
        try:
            await self.client.load_data_type_definitions()
            self.mv = await self.client.get_namespace_index(MACHINE_VISION)
            self.vision = await self.find_vision_system()
        except BaseException:
            await self.client.disconnect()
            raise
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        await self.client.disconnect()

    async def find_vision_system(self):
        """The Objects folder's child whose type is VisionSystemType (the station's)."""
        vision_type = ua.NodeId(1003, self.mv)
        for child in await self.client.nodes.objects.get_children():
            if await child.read_type_definition() == vision_type:
                return child
        raise AssertionError("no VisionSystemType object under Objects")

    async def method(self, name: str):
        path = [f"{self.mv}:{part}" for part in (*METHOD_PLACES[name], name)]
        return await self.vision.get_child(path)

    async def owner(self, name: str):
        return await self.vision.get_child([f"{self.mv}:{part}" for part in METHOD_PLACES[name]])

    async def call(self, name: str, *arguments: Any) -> list[Any]:
        """Call a method; its outputs (a Bad status code raises asyncua's exception for it)."""
        result = await self.call_raw(name, *arguments)
        result.StatusCode.check()
        return [variant.Value for variant in result.OutputArguments]

    async def call_raw(self, name: str, *arguments: Any) -> ua.CallMethodResult:
        request = ua.CallMethodRequest()
        request.ObjectId = (await self.owner(name)).nodeid
        request.MethodId = (await self.method(name)).nodeid
        request.InputArguments = [value if isinstance(value, ua.Variant) else ua.Variant(value) for value in arguments]
        (result,) = await self.client.uaclient.call([request])
        return result

    async def state(self) -> tuple[str, str | None]:
        machine = await self.vision.get_child(f"{self.mv}:VisionStateMachine")
        vision = (await (await machine.get_child("0:CurrentState")).read_value()).Text
        automatic = await (await machine.get_child([f"{self.mv}:AutomaticModeStateMachine", "0:CurrentState"])
                           ).read_data_value(raise_on_bad_status=False)
        return vision, automatic.Value.Value.Text if automatic.StatusCode.is_good() else None

    async def subscribe(self, *event_types: str, interval_ms: float = 100) -> None:
        """Subscribe to the VisionSystem's events of these types (an event reaches the client at the server's
        next publishing cycle: up to ``interval_ms`` later)."""
        paths = {"StateChangedEventType": ["0:TransitionEventType"],
                 "VisionWarningConditionType": ["0:ConditionType", "0:AcknowledgeableConditionType",
                                                f"{self.mv}:VisionConditionType"]}
        types = [await self.client.nodes.base_event_type.get_child([*paths.get(name, []), f"{self.mv}:{name}"])
                 for name in event_types]
        subscription = await self.client.create_subscription(interval_ms, self)
        await subscription.subscribe_events(self.vision, types)

    def event_notification(self, event) -> None:
        self.event_times.append(time.perf_counter())
        self.events.append({**event.get_event_props_as_fields_dict(), "_type": event.EventType})

    def status_change_notification(self, status) -> None:
        self.status_changes.append(status)

    def of_type(self, name: str) -> list[dict[str, Any]]:
        wanted = ua.NodeId({"ResultReadyEventType": 1024, "StateChangedEventType": 1018, "JobStartedEventType": 1013,
                            "ReadyEventType": 1023, "AcquisitionDoneEventType": 1025,
                            "RecipePreparedEventType": 1022, "VisionWarningConditionType": 1034}[name], self.mv)
        return [event for event in self.events if event["_type"] == wanted]

    async def wait_for(self, condition, timeout_s: float = 30.0) -> bool:
        deadline = time.monotonic() + timeout_s
        while not condition():
            if time.monotonic() > deadline:
                return False
            await asyncio.sleep(0.02)
        return True


def value(event: dict[str, Any], name: str) -> Any:
    """An event field's value (the fields come as Variants)."""
    field = event.get(name)
    return field.Value if isinstance(field, ua.Variant) else field
