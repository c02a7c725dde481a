"""The service's settings: one pydantic-settings class, environment prefix ``TEACHPATH_``."""

from __future__ import annotations

import math
import os
import secrets
from pathlib import Path
from typing import TYPE_CHECKING

from pydantic import Field, PrivateAttr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from drivers.scanning.limits import DEFAULT_MAX_FRAME_PIXELS, DEFAULT_MAX_PIXELS

if TYPE_CHECKING:
    from recon.kinematics import DHCalibration


class Settings(BaseSettings):
    """Everything the service can be told. Built in the app factory; tests pass their own."""

    model_config = SettingsConfigDict(env_prefix="TEACHPATH_", extra="forbid")

    host: str = Field("127.0.0.1", description="address to listen on (loopback unless told)")
    port: int = Field(8000, ge=0, le=65535)
    data_dir: Path = Field(Path("teachpath_data"), description="database, arrays, token")
    database_url: str | None = Field(
        None,
        description="SQLAlchemy URL; default SQLite in data_dir (a postgresql:// URL works too)",
    )
    token: str | None = Field(
        None,
        description="access token; default generated on first "
        "start and kept in data_dir/token (mode 0600)",
    )
    max_upload_mb: float = Field(200.0, gt=0, description="largest accepted upload")
    max_json_kb: float = Field(
        256.0, ge=16, le=65536, description="largest accepted JSON request body (KB)"
    )
    # Two uploads of the largest size at once. Each byte in flight costs this process a little
    # more than a byte (the upload, and its copy on the way to the parse's worker; the parsed
    # arrays stay out of it): 20 uploads of 24 MB at once took it from 135 MB to 742 MB without
    # a cap, to 556 MB at 400 (16 taken, 4 refused) and to 265 MB at 100.
    max_uploads_in_flight_mb: float = Field(
        400.0,
        gt=0,
        description="uploads being received, parsed and stored at once, in MB; one more is "
        "refused with 503 and Retry-After (at least max_upload_mb)",
    )
    max_speed_m_s: float = Field(0.25, gt=0, description="TCP speed cap for real-arm execution")
    max_scan_unpacked_mb: float = Field(
        2048.0, gt=0, description="largest size a zipped RGB-D scan upload may unpack to"
    )
    max_scan_decode_s: float = Field(
        300.0,
        gt=0,
        description="longest the parse of a scan upload may take (its process is ended then), "
        "a RealSense bag's decoding included",
    )
    max_scan_frame_pixels: int = Field(
        DEFAULT_MAX_FRAME_PIXELS,
        gt=0,
        description="largest RGB-D depth image (width x height), refused before decoding; "
        "depth cameras stay well below 4096 x 4096",
    )
    max_scan_pixels: int = Field(
        DEFAULT_MAX_PIXELS,
        gt=0,
        description="most pixels over all frames of an RGB-D scan upload, refused before decoding",
    )
    # Twice what the largest upload needs: the parse's interpreter with Open3D maps 0.5 GB of
    # address space; a 200 MB binary PLY (17.5 M points) peaked at 2.0 GB (1.6 GB resident), a
    # 4096 x 4096 depth frame at 1.4 GB (measured through service.tasks.ParseScan).
    max_parse_memory_mb: float = Field(
        4096.0,
        gt=0,
        description="address space of the process an upload (trace or scan) is parsed in, MB; "
        "more is a 413",
    )
    # Each parse is a child process of up to max_parse_memory_mb: two at once fit this machine
    # twice over and keep a core for the event loop's other requests.
    max_parallel_parses: int = Field(
        2,
        ge=1,
        le=16,
        description="uploads parsed at once (each in a process of its own); more wait their turn",
    )
    max_trace_parse_s: float = Field(
        300.0,
        gt=0,
        description="longest the parse of a trace upload may take (its process is ended then)",
    )
    # Each NatNet capture runs a receiver process of its own (ten captures had the service at
    # twelve processes); one pen needs one capture, two leave room for a second session.
    max_live_captures: int = Field(
        2, ge=0, description="live (NatNet) captures running at once; one more is a 409"
    )
    cpu_workers: int = Field(
        1,
        ge=1,
        le=8,
        description="processes for reconstruction and "
        "planning (the event loop keeps a core on a 2-core machine)",
    )
    warm_workers: bool = Field(
        True,
        description="start the worker processes with the service and import the "
        "reconstruction and planning code in them, so that the first job does not wait for it",
    )
    cors_origins: list[str] = Field(default_factory=list, description="closed by default")
    ur_host: str | None = Field(None, description="controller address for backend ur_rtde")
    ur_robot: str = Field("ur5e", description="the model of the arm at ur_host")
    ur_watchdog_hz: float = Field(
        2.0,
        ge=0.5,
        le=100.0,
        description="during a motion the controller stops the program when this service has "
        "written nothing to it for 1/ur_watchdog_hz s (a hung or killed worker)",
    )
    ur_stale_after_s: float = Field(
        0.5,
        gt=0,
        le=5.0,
        description="a run on the arm stops and fails when the controller's state has not "
        "changed for this long (s): the link counts as lost",
    )
    ur_rt_priority: int = Field(
        80,
        ge=0,
        le=99,
        description="realtime priority (SCHED_FIFO) of the servoJ loop while it streams; 0: "
        "normal priority (a machine that also runs the controller's simulator, or a container "
        "without CAP_SYS_NICE)",
    )
    ur_calibration: Path | None = Field(
        None,
        description="the arm's own kinematics calibration: its controller's calibration.conf "
        "(copied from /root/.urcontrol/); plans solve their joints with it (without it UR's "
        "nominal model, millimetres off on a real arm)",
    )
    _arm_calibration: DHCalibration | None = PrivateAttr(default=None)
    home_q_rad: tuple[float, float, float, float, float, float] = Field(
        (0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0),
        description="where plans start on the simulated arm (rad)",
    )
    robot_poll_s: float = Field(0.2, gt=0.01, le=5.0, description="how often the arm is read")
    keep_out_boxes: list[tuple[float, float, float, float, float, float]] = Field(
        default_factory=list,
        description="boxes the arm and tool must keep out of, base frame: "
        "x_min, y_min, z_min, x_max, y_max, z_max (m)",
    )
    mount_up: tuple[float, float, float] = Field(
        (0.0, 0.0, 1.0),
        description="how the arm is mounted: up (away from the earth's centre) in its base "
        "frame, as in its installation: 0,0,1 floor, 0,0,-1 ceiling, horizontal on a wall; "
        "plans made here default to it",
    )
    cell_planes: list[tuple[float, float, float, float]] = Field(
        default_factory=list,
        description="surfaces of the cell besides the one the base stands on (a wall, the floor "
        "below a wall- or ceiling-mounted arm), base frame: nx, ny, nz, d; the arm keeps to "
        "n . p >= d",
    )
    cell_name: str | None = Field(
        None,
        min_length=1,
        max_length=200,
        description="the name this arm's cell is stored under once edited in the pendant "
        "(instances for different arms on one database keep theirs apart; one instance drives "
        "an arm); default: the arm's model and address, or 'simulated'",
    )
    demo: bool = Field(False, description="create the demo session on start if missing")
    guide_dir: Path = Field(
        Path(__file__).resolve().parent.parent / "site",
        description="the documentation site `make docs` builds, served at /guide",
    )

    @field_validator("keep_out_boxes")
    @classmethod
    def _boxes(
        cls, value: list[tuple[float, float, float, float, float, float]]
    ) -> list[tuple[float, float, float, float, float, float]]:
        if value:
            from service.cell import check_shapes

            # The pendant's own checks, raised at start-up, not at planning: a cell set here
            # can be saved unchanged from the pendant.
            check_shapes(list(value), [])
        return value

    @field_validator("mount_up")
    @classmethod
    def _mount_up(cls, value: tuple[float, float, float]) -> tuple[float, float, float]:
        length = math.sqrt(sum(v * v for v in value))
        if not 0.5 <= length <= 1.5:
            raise ValueError(
                f"mount_up must be a direction, a unit vector (0,0,1 for a floor mount), got "
                f"{value}"
            )
        return value

    @field_validator("cell_planes")
    @classmethod
    def _planes(
        cls, value: list[tuple[float, float, float, float]]
    ) -> list[tuple[float, float, float, float]]:
        if value:
            from service.cell import check_shapes

            check_shapes([], list(value))
        return value

    @model_validator(mode="after")
    def _in_flight_holds_an_upload(self) -> Settings:
        if self.max_uploads_in_flight_mb < self.max_upload_mb:
            raise ValueError(
                f"max_uploads_in_flight_mb ({self.max_uploads_in_flight_mb:g}) is below "
                f"max_upload_mb ({self.max_upload_mb:g}): an upload of the largest size could "
                "never be accepted; raise it to at least max_upload_mb"
            )
        return self

    @field_validator("data_dir")
    @classmethod
    def _absolute(cls, value: Path) -> Path:
        return value.expanduser().resolve()

    @model_validator(mode="after")
    def _calibration_is_this_arms(self) -> Settings:
        # Read and checked once, at start: a server must not plan for an arm it cannot model,
        # and a file changed later does not change the arm under a running server.
        self._arm_calibration = None
        if self.ur_calibration is not None:
            from drivers.errors import InputFileError
            from drivers.robot.ur_calibration import read_ur_calibration
            from recon import kinematics

            try:
                calibration = read_ur_calibration(self.ur_calibration)
                kinematics.with_calibration(kinematics.model(self.ur_robot), calibration)
            except InputFileError as exc:
                raise ValueError(f"ur_calibration: {exc}") from None
            self._arm_calibration = calibration
        return self

    @property
    def arm_calibration(self) -> DHCalibration | None:
        """The arm's :class:`recon.kinematics.DHCalibration` read from ``ur_calibration`` at
        start (None without one), checked against ``ur_robot``."""
        return self._arm_calibration

    @property
    def cell_key(self) -> str:
        """The name this arm's edited cell is stored under (``cell_name`` or one made of the
        arm's model and address)."""
        if self.cell_name:
            return self.cell_name
        return f"{self.ur_robot}@{self.ur_host}" if self.ur_host else "simulated"

    @property
    def db_url(self) -> str:
        return self.database_url or f"sqlite:///{self.data_dir / 'teachpath.db'}"

    def access_token(self) -> str:
        """The configured token, or the one stored in data_dir (created on first use)."""
        if self.token:
            return self.token
        path = self.data_dir / "token"
        if path.exists():
            return path.read_text().strip()
        self.data_dir.mkdir(parents=True, exist_ok=True)
        token = secrets.token_urlsafe(24)
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as handle:
            handle.write(token + "\n")
        return token
