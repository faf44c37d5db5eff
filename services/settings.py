"""The one configuration object of the thermofield service, read from ``THERMOFIELD_*`` environment variables.

Every process (``thermofield serve``, ``api``, ``worker``, ``gateway``) builds its
configuration here and nowhere else. Unset locations derive from ``data_dir``, so the
embedded default needs no configuration at all; the scaled-out deployment sets
``THERMOFIELD_DATABASE_URL``, ``THERMOFIELD_BROKER_URL`` and the artifact directory.
See docs/api.md ("Configuration").
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Literal, NamedTuple

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict


class StationDrivers(NamedTuple):
    """The driver of each device of the station."""

    camera: Literal["simulated", "oak", "genicam"]
    thermal: Literal["simulated", "oak", "genicam"]
    projector: Literal["simulated", "display"]


# What GATEWAY_DRIVER (``thermofield gateway --driver``) stands for, device by device.
_GATEWAY_DRIVERS = {"simulated": StationDrivers("simulated", "simulated", "simulated"),
                    "oak": StationDrivers("oak", "oak", "display"),
                    "genicam": StationDrivers("genicam", "genicam", "display")}


class Settings(BaseSettings):
    """Service configuration; each field is the environment variable ``THERMOFIELD_<NAME>``."""

    model_config = SettingsConfigDict(env_prefix="THERMOFIELD_", extra="ignore")

    data_dir: Path = Field(Path("thermofield-data"), description="Root of the embedded database and artifacts.")
    database_url: str | None = Field(
        None, description="SQLAlchemy URL; default SQLite (WAL) at DATA_DIR/thermofield.db."
    )
    database_schema: str | None = Field(
        None, description="PostgreSQL schema holding the tables (isolates deployments sharing one database)."
    )
    broker_url: str | None = Field(
        None, description="RabbitMQ AMQP URL; unset means the embedded in-process worker."
    )
    job_queue: str = Field("thermofield", pattern=r"^[A-Za-z0-9_.-]+$",
                           description="Broker queue of the jobs (deployments sharing a RabbitMQ use different ones).")
    artifact_dir: Path | None = Field(None, description="Content-addressed artifact store; default DATA_DIR/artifacts.")

    api_host: str = Field("127.0.0.1", description="Address the HTTP API binds to.")
    api_port: int = Field(8000, ge=0, le=65535, description="Port of the HTTP API.")

    gateway_url: str = Field("http://127.0.0.1:8001", description="Base URL of the device gateway.")
    gateway_host: str = Field("127.0.0.1", description="Address the device gateway binds to.")
    gateway_port: int = Field(8001, ge=0, le=65535, description="Port of the device gateway.")
    gateway_driver: Literal["simulated", "oak", "genicam"] = Field(
        "simulated", description="Devices behind the gateway, unless chosen per device below: the virtual rig; OAK "
                                 "cameras and a display projector; or GenICam cameras and a display projector.")
    camera_driver: Literal["simulated", "oak", "genicam"] | None = Field(
        None, description="Driver of the camera filming the patterns; default GATEWAY_DRIVER's.")
    thermal_driver: Literal["simulated", "oak", "genicam"] | None = Field(
        None, description="Driver of the thermal camera; default GATEWAY_DRIVER's.")
    projector_driver: Literal["simulated", "display"] | None = Field(
        None, description="Driver of the projector; default GATEWAY_DRIVER's (display unless simulated).")
    simulated_scene: Path | None = Field(
        None, description="Scene file the simulated gateway films (docs/simulator.md; with the temperature and "
                          "optics blocks of docs/hot-parts.md a glowing part); default the forging preset.")
    simulated_station_heads: int = Field(
        0, ge=0, le=12, description="Heads of the simulated station around the hot shaft (docs/station.md): the "
                                    "simulated gateway films them one after another; 0: the single-head station.")
    simulated_station_scale: float = Field(
        1.0, gt=0, le=1, description="Shrinks the simulated station's images and focal lengths (quick runs).")
    simulated_lost_head: str | None = Field(
        None, description="Fault drills: the simulated station's head whose camera is lost in the first capture.")
    oak_camera_id: str | None = Field(None, description="OAK filming the patterns (MxId, IP or name); default the only one.")
    oak_thermal_id: str | None = Field(None, description="OAK-T thermal camera (MxId, IP or name); default the only one.")
    camera_socket: str = Field("CAM_A", pattern=r"^CAM_[A-J]$", description="Board socket of the OAK camera's sensor.")
    camera_lens_position: int = Field(
        130, ge=0, le=255, description="Manual focus (0..255) the OAK camera is locked at: the one it was calibrated at."
    )
    thermal_socket: str = Field("CAM_E", pattern=r"^CAM_[A-J]$", description="Board socket of the OAK-T's sensor.")
    thermal_gain_mode: Literal["low", "high"] = Field(
        "low", description="OAK-T gain: low measures up to 900 K, high up to 500 K with less noise."
    )
    camera_width: int = Field(1280, gt=0, description="Width of the camera frames (OAK output; GenICam region).")
    camera_height: int = Field(800, gt=0, description="Height of the camera frames (OAK output; GenICam region).")
    camera_exposure_us: int = Field(8000, gt=0, description="Manual exposure time of the camera, microseconds.")
    camera_iso: int = Field(100, ge=100, le=1600, description="Manual sensitivity of the OAK camera.")
    genicam_camera: str | None = Field(
        None, description="Aravis device id (as arv-tool-0.8 lists it) or IP address of the GenICam camera.")
    genicam_pixel_format: Literal["Mono8", "Mono10", "Mono12", "Mono14", "Mono16"] = Field(
        "Mono8", description="Pixel format of the GenICam camera, kept at its full depth (uint16 above 8 bits).")
    genicam_trigger: str = Field(
        "Software", pattern=r"^(Software|Line[0-9]+)$",
        description="What triggers each pattern's GenICam frame: Software, or the input line the projector's sync "
                    "out is wired to, e.g. Line1 (docs/devices.md).")
    camera_gain: float | None = Field(None, description="GenICam camera gain (its Gain feature, dB on most "
                                                        "cameras); default the camera's.")
    camera_offset_x: int = Field(0, ge=0, description="Left edge of the GenICam camera's region on its sensor.")
    camera_offset_y: int = Field(0, ge=0, description="Top edge of the GenICam camera's region on its sensor.")
    genicam_thermal: str | None = Field(
        None, description="Aravis device id or IP address of the GenICam thermal camera (radiometric frames).")
    genicam_thermal_pixel_format: Literal["Mono8", "Mono10", "Mono12", "Mono14", "Mono16"] = Field(
        "Mono16", description="Pixel format of the GenICam thermal camera's temperature-linear counts.")
    genicam_thermal_kelvin_per_count: float = Field(
        0.01, gt=0, description="Kelvin per count of the GenICam thermal camera's temperature-linear output, as "
                                "its manual states (e.g. 0.01 or 0.1).")
    genicam_thermal_offset_k: float = Field(0.0, description="Kelvin at count 0 of the GenICam thermal camera.")
    camera_exposure_mode: Literal["fixed", "auto", "hdr"] = Field(
        "fixed", description="Scan exposure: the camera's own, metered for a glowing part (glow plus pattern "
                             "below saturation), or metered and HDR-merged (docs/hot-parts.md).")
    hot_part_sequence: bool = Field(
        False, description="The gateway's sequence closes with a second black frame, so that a cooling part's "
                           "drifting glow is interpolated and removed (docs/hot-parts.md).")
    projector_display: int = Field(0, ge=0, description="Display number the projector is connected as.")
    projector_width: int = Field(1280, gt=0, description="Native width of the projector.")
    projector_height: int = Field(800, gt=0, description="Native height of the projector.")
    projector_settle_ms: float | None = Field(
        None, ge=0, description="Wait after showing a pattern before filming; default the driver's (100 ms, 0 simulated)."
    )

    rerun_host: str = Field("127.0.0.1", description="Address the Rerun gRPC proxy binds to / is reached at.")
    rerun_port: int = Field(9876, ge=0, le=65535, description="Port of the Rerun gRPC proxy.")
    rerun_web_port: int | None = Field(
        9090, ge=1, le=65535, description="Port of Rerun's web viewer, served by the embedded service's proxy on "
                                          "THERMOFIELD_RERUN_HOST (docs/streaming.md); empty: none.")

    mqtt_host: str | None = Field("127.0.0.1", description="MQTT broker host; empty disables events.")
    mqtt_port: int = Field(1883, ge=1, le=65535, description="MQTT broker port.")
    opcua_endpoint: str | None = Field(
        None, description="opc.tcp://host:port/path the OPC UA server (OPC 40100-1 Machine Vision: state machines, "
                          "recipes, configurations, jobs, results) listens at, in `thermofield serve` or, scaled "
                          "out, `thermofield api`; unset: no OPC UA server (docs/opcua.md).")
    opcua_security_policy: Literal["Basic256Sha256", "None"] = Field(
        "Basic256Sha256", description="Basic256Sha256: clients connect signed and encrypted only (Sign&Encrypt) and "
                                      "their certificates must be trusted; None: unsigned and unencrypted, API keys "
                                      "in the clear (a test bench only).")
    opcua_pki_dir: Path | None = Field(
        None, description="The OPC UA server's certificate and key made on its first start, and trusted/ (the "
                          "client certificates it accepts); default DATA_DIR/opcua.")
    opcua_certificate: Path | None = Field(
        None, description="The operator's server certificate (DER or PEM) instead of the one the server makes; "
                          "with THERMOFIELD_OPCUA_PRIVATE_KEY.")
    opcua_private_key: Path | None = Field(None, description="The private key (PEM) of THERMOFIELD_OPCUA_CERTIFICATE.")
    site: str = Field("plant", pattern=r"^[A-Za-z0-9_-]+$", description="First level of the MQTT topic tree.")
    station: str = Field("station1", pattern=r"^[A-Za-z0-9_-]+$", description="Second level of the MQTT topic tree.")

    rate_limit_per_s: float = Field(
        50.0, ge=0, description="Requests per second each API key may make on average, per API process (0: no limit)."
    )
    rate_limit_burst: int = Field(100, ge=1, description="Requests an API key may make at once above its rate.")

    max_image_bytes: int = Field(64 << 20, gt=0, description="Largest uploaded image (413 beyond).")
    max_upload_bytes: int = Field(
        512 << 20, gt=0, description="Largest multipart upload, all its files together (413 payload-too-large "
                                     "beyond).")
    max_body_bytes: int = Field(
        1 << 20, gt=0, description="Largest request body that is not a multipart upload, e.g. JSON (413 "
                                   "payload-too-large beyond).")
    max_image_pixels: int = Field(
        1 << 25, gt=0, description="Most pixels an uploaded image may declare in its header (413 beyond, before "
                                   "it is decoded); board images must also have their device's size.")
    max_mesh_triangles: int = Field(
        10_000_000, gt=0, description="Most triangles an uploaded mesh may declare (413 beyond, before it is read).")
    decode_memory_bytes: int = Field(
        1 << 30, gt=0, description="Memory one upload's decoding may take: what its headers declare is refused "
                                   "beyond it (413) before decoding, and the decoding process is capped at it.")
    decode_processes: int = Field(
        2, ge=1, description="Uploads decoded at once, each in a process of its own (the API's event loop never "
                             "decodes); further uploads wait their turn.")
    decode_timeout_s: float = Field(60.0, gt=0, description="Seconds one upload's decoding may take (422 beyond).")
    max_header_bytes: int = Field(
        32 << 10, ge=1024, description="Largest request line and headers of one HTTP request (431 beyond).")
    header_timeout_s: float = Field(
        10.0, gt=0, description="Seconds a client has to send a request's line and headers (408 beyond).")
    body_timeout_s: float = Field(
        300.0, gt=0, description="Seconds a client has to send a request's body once its headers are in (408 "
                                 "beyond): a 512 MiB upload at 20 Mbit/s.")
    auth_failure_rate_per_s: float = Field(
        1.0, ge=0, description="Failed authentications per second a client address may make on average, per API "
                               "process, before 429 (0: no limit).")
    auth_failure_burst: int = Field(20, ge=1, description="Failed authentications a client address may make at once.")
    min_free_bytes: int = Field(
        1 << 30, ge=0, description="Free space the artifact store needs for /readyz to say ready (a scan takes ~100 MB)."
    )
    job_queue_bound: int = Field(
        100, ge=0, description="Jobs that may wait to run at once; a new one beyond is refused with 503 and "
                               "Retry-After (0: no bound).")
    idempotency_ttl_s: float = Field(86400.0, gt=0, description="How long an Idempotency-Key's answer is replayed.")
    retention_keep_scans: int = Field(100, ge=0, description="Scans per station that keep their artifacts, newest first.")
    retention_keep_days: float = Field(7.0, ge=0, description="Days a scan keeps its artifacts (whatever its rank).")
    retention_raw_frames_days: float = Field(1.0, ge=0, description="Days a scan keeps its raw frames.")
    retention_blob_grace_s: float = Field(
        3600.0, ge=0, description="Seconds a blob no row names is kept before the sweep deletes it (a scan in flight "
                                  "stores its blobs before its row names them): what an expired scan's files wait.")
    maintenance_interval_s: float = Field(
        3600.0, ge=0, description="Seconds between retention runs in the API processes (0: never)."
    )

    worker_processes: int = Field(2, ge=1, description="Worker processes started by `thermofield worker`.")
    worker_threads: int = Field(1, ge=1, description="Jobs run at once per worker process.")
    compute_threads: int = Field(2, ge=1, description="Numeric threads (numba, OpenCV, BLAS) per worker process.")
    warm_up: bool = Field(True, description="Compile the kernels and build the active calibration's tables when a "
                                            "worker starts (/readyz answers 503 meanwhile), so the first scan is fast.")

    @field_validator("rerun_web_port", mode="before")
    @classmethod
    def _empty_is_none(cls, value: object) -> object:
        return None if value == "" else value

    @property
    def resolved_database_url(self) -> str:
        return self.database_url or f"sqlite:///{(self.data_dir / 'thermofield.db').resolve()}"

    @property
    def resolved_artifact_dir(self) -> Path:
        return self.artifact_dir or self.data_dir / "artifacts"

    @property
    def retention_policy(self):
        from services.storage.retention import RetentionPolicy

        return RetentionPolicy(keep_scans=self.retention_keep_scans, keep_days=self.retention_keep_days,
                               raw_frames_days=self.retention_raw_frames_days,
                               idempotency_ttl_s=self.idempotency_ttl_s, blob_grace_s=self.retention_blob_grace_s)

    @property
    def station_drivers(self) -> StationDrivers:
        """The driver of each device: chosen per device, else GATEWAY_DRIVER's."""
        default = _GATEWAY_DRIVERS[self.gateway_driver]
        return StationDrivers(camera=self.camera_driver or default.camera,
                              thermal=self.thermal_driver or default.thermal,
                              projector=self.projector_driver or default.projector)

    @property
    def topic_prefix(self) -> str:
        return f"{self.site}/{self.station}"


@lru_cache
def get_settings() -> Settings:
    """The process's settings, read once from the environment."""
    return Settings()


def thread_environment(threads: int) -> dict[str, str]:
    """The numeric libraries' thread variables for ``threads`` threads, for the environment of processes
    about to import them (the spawned worker processes)."""
    return {name: str(threads) for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                                            "NUMBA_NUM_THREADS")}
