"""The daemon's configuration (YAML) as pydantic v2 models, and the body of a TUNE request.

A config file lists the loops the daemon owns, the API tokens and where the
history is kept (docs/daemon.md has a full example). :func:`load_config`
reads and validates it; every problem is a :class:`ConfigError` whose message
names the file, the path inside it (``loops[1].tuning.amp``) and what is
wrong — never a traceback. Relative paths (register maps, DBCs, the history
database) are relative to the config file's folder.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

if TYPE_CHECKING:  # the session's module is loaded only when a session's hand-back is made
    from drivers.simplc import SimulatedPlc

    from autotuner.service.link_session import HandBack

# How long a session waits for the history to record what must be durable before it goes on (the saved state
# before the loop is touched, a gains intent before the write), and for its end to be recorded before the loop is
# idle again, wall seconds: `record_wait`'s default, the daemon's and `autotuner tune --config`'s. Beyond it: the
# loop is not touched / the gains are not written, and those records are dropped, never written late / the end is
# recorded later (retried in the history's thread; never on the event loop).
RECORD_WAIT = 10.0


class ConfigError(ValueError):
    """The config file cannot be used; the message says where and why."""


class Strict(BaseModel):
    """Unknown keys are errors (a typo must not silently fall back to a default)."""

    model_config = ConfigDict(extra="forbid", frozen=True)


# Largest relay amplitude of a loop without finite MV limits (and of ``tune --link`` without --mv-limits), MV units:
# the whole range of an MV in percent. A relay amplitude is written to a live controller; it is never unbounded.
DEFAULT_MAX_AMP = 100.0
# The global bounds every TUNE request is held to (published in the OpenAPI schema), MV and PV units: large enough
# for any plant's engineering units, finite so a client's arithmetic stays finite. Each loop's own bounds (below)
# are tighter and are published in its status (``bounds``).
AMP_MAX = 1e6
HYSTERESIS_MAX = 1e6
# A loop's largest hysteresis, as a fraction of the span of its PV limits: the PV must leave SP ± hysteresis on
# both sides every half period, a swing of at least twice the hysteresis, and needs room beyond it (overshoot, an
# SP off centre) within the limits; a quarter leaves half the span for that.
HYSTERESIS_SPAN_FRACTION = 0.25
# The largest hysteresis of a loop without finite PV limits and without tuning.max_hysteresis, PV units: a quarter
# of 0-100 (a PV in percent).
DEFAULT_MAX_HYSTERESIS = 25.0

Controller = Literal["PI", "PID"]
PositiveFloat = Annotated[float, Field(gt=0.0, allow_inf_nan=False)]
Amplitude = Annotated[float, Field(gt=0.0, le=AMP_MAX, allow_inf_nan=False)]
Hysteresis = Annotated[float, Field(ge=0.0, le=HYSTERESIS_MAX, allow_inf_nan=False)]



class Tuning(Strict):
    """Defaults of a loop's experiment and design.

    amp: relay amplitude, MV units; hysteresis: PV units (None: 3σ of the
    measured noise); phase: lag of the identified point, degrees; ms: maximum
    sensitivity of the design; time_limit: longest experiment, plant seconds.
    max_amp: largest relay amplitude a request may ask for, MV units, when the
    loop has no finite MV limits (with them, the bound is their span).
    max_hysteresis: largest hysteresis a request may ask for, PV units (None:
    :data:`HYSTERESIS_SPAN_FRACTION` of the span of the PV limits, else
    :data:`DEFAULT_MAX_HYSTERESIS`).
    """

    controller: Controller = "PI"
    amp: Amplitude = 1.0
    hysteresis: Hysteresis | None = None
    phase: Annotated[float, Field(ge=90.0, le=170.0)] = 135.0
    ms: Annotated[float, Field(ge=1.05, le=4.0)] = 1.4
    time_limit: PositiveFloat = 7200.0
    max_amp: Amplitude = DEFAULT_MAX_AMP
    max_hysteresis: Hysteresis | None = None


def amp_bound(mv_limits: tuple[float, float], max_amp: float = DEFAULT_MAX_AMP) -> float:
    """The largest relay amplitude, MV units: the span of ``mv_limits`` when both are finite, else ``max_amp``
    (never above :data:`AMP_MAX`)."""
    low, high = mv_limits
    return min(high - low if math.isfinite(low) and math.isfinite(high) else max_amp, AMP_MAX)


def hysteresis_bound(pv_limits: tuple[float, float], max_hysteresis: float | None = None) -> float:
    """The largest relay hysteresis, PV units: ``max_hysteresis`` when configured, else
    :data:`HYSTERESIS_SPAN_FRACTION` of the span of ``pv_limits`` when both are finite, else
    :data:`DEFAULT_MAX_HYSTERESIS` (never above :data:`HYSTERESIS_MAX`)."""
    low, high = pv_limits
    if max_hysteresis is not None:
        bound = max_hysteresis
    elif math.isfinite(low) and math.isfinite(high):
        bound = HYSTERESIS_SPAN_FRACTION * (high - low)
    else:
        bound = DEFAULT_MAX_HYSTERESIS
    return min(bound, HYSTERESIS_MAX)


class TuneRequest(BaseModel):
    """Body of ``POST /loops/{id}/tune``: any field left out takes the loop's configured default.

    Strict: a value of the wrong JSON type (``"apply": "yes"``, ``"apply": 0``,
    ``"amp": "5"``) is refused, never coerced — these fields drive a live
    controller. (The YAML config keeps pydantic's lax conversions: lists to
    tuples, strings to paths.) Every bound here is published in the OpenAPI
    schema; ``amp`` and ``hysteresis`` are also bounded per loop
    (:func:`amp_bound`, :func:`hysteresis_bound`), which only the daemon knows
    and publishes in each loop's status (``bounds``).
    """

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)

    controller: Controller | None = Field(None, description="controller to design, PI or PID", examples=["PI"])
    amp: Amplitude | None = Field(None, description=f"relay amplitude, MV units (> 0, ≤ {AMP_MAX:g}; and at most the "
                                  "loop's bounds.amp, in its status)", examples=[5.0])
    hysteresis: Hysteresis | None = Field(
        None, description=f"relay hysteresis, PV units (≥ 0, ≤ {HYSTERESIS_MAX:g}; and at most the loop's "
        "bounds.hysteresis, in its status; absent: 3σ of the noise measured first)", examples=[0.1])
    phase: Annotated[float, Field(ge=90.0, le=170.0)] | None = Field(
        None, description="phase lag of the point to identify, degrees (90–170)", examples=[135.0])
    ms: Annotated[float, Field(ge=1.05, le=4.0)] | None = Field(
        None, description="maximum sensitivity the design aims at (1.05–4)", examples=[1.4])
    apply: bool | None = Field(None, description="write the gains to the controller on success", examples=[False])


Range = tuple[float, float]


class Limits(Strict):
    """Safety limits of the experiment: PV range (abort outside it) and MV range, engineering units."""

    pv: Range = (-math.inf, math.inf)
    mv: Range = (-math.inf, math.inf)

    @field_validator("pv", "mv")
    @classmethod
    def _ordered(cls, value: Range) -> Range:
        if not value[0] < value[1]:
            raise ValueError(f"must be [low, high] with low < high, got [{value[0]}, {value[1]}]")
        return value


# A unit as shown beside a value: printable text, no control characters (it goes into a page and an OPC UA node).
UnitText = Annotated[str, Field(max_length=16, pattern=r"^[^\x00-\x1f\x7f]*$")]


class Units(Strict):
    """A loop's engineering units and display (docs/daemon.md, "Units"): the page and OPC UA show them.

    pv: unit of the PV and SP (and of the hysteresis), e.g. ``°C``; mv: unit of
    the MV (and of the relay amplitude), e.g. ``%``; "" (the default): no unit
    shown. decimals: digits after the decimal point of PV, SP and MV values
    (0–6); None (the default): 4 significant digits. pv_range, mv_range: the
    trend's fixed axis ranges [low, high], in those units; None (the default):
    the axis fits the data. Display only: the experiment's safety limits are
    ``limits``.
    """

    pv: UnitText = ""
    mv: UnitText = ""
    decimals: Annotated[int, Field(ge=0, le=6, strict=True)] | None = None
    pv_range: Range | None = None
    mv_range: Range | None = None

    @field_validator("pv_range", "mv_range")
    @classmethod
    def _ordered(cls, value: Range | None) -> Range | None:
        if value is not None and not (math.isfinite(value[0]) and math.isfinite(value[1]) and value[0] < value[1]):
            raise ValueError(f"must be [low, high], finite, with low < high, got [{value[0]}, {value[1]}]")
        return value

    def as_json(self) -> dict[str, Any]:
        """The ``units`` of a loop's REST status (ranges as [low, high] lists or null)."""
        return {"pv": self.pv, "mv": self.mv, "decimals": self.decimals,
                "pv_range": None if self.pv_range is None else list(self.pv_range),
                "mv_range": None if self.mv_range is None else list(self.mv_range)}


class SimPlant(Strict):
    """A simulated PLC run inside the daemon: what a plant file's loop gives (docs/health.md, "The plant file"),
    without its id and description, which are the loop's own: ``plant`` under a PID unit, white PV noise
    (``noise``, σ PV units; ``seed``), its ``mode`` (AUTO or MAN), its PI ``gains`` and ``detune`` factors, its
    ``faults`` (a sticky valve, a deadband, loads, a sinusoid, a frozen PV sensor) and ``ts``, the plant seconds
    per tick (None: the loop's ``ts`` over ``PLANT_TICKS_PER_SAMPLE``).

    Validated by the plant file's own reader (:func:`drivers.plant_file.simulated_plc`): one set of rules, and
    its messages name the key (``faults.stiction.j: must be a finite number``).
    """

    plant: str
    ts: float | None = None
    noise: float = 0.0
    seed: int = 0
    mode: str = "AUTO"
    gains: dict[str, Any] = {}
    detune: dict[str, Any] = {}
    faults: dict[str, Any] = {}

    @model_validator(mode="after")
    def _builds(self) -> SimPlant:
        self.plc(1.0)  # the plant file's checks; the PlantFileError (a ValueError) names the key
        return self

    def plc(self, tick: float) -> SimulatedPlc:
        """A new simulated PLC of this plant, ticking every ``ts`` plant seconds (else every ``tick``)."""
        from drivers.plant_file import simulated_plc

        data = self.model_dump(exclude_defaults=True)
        return simulated_plc("", data, ts=tick)


# Bounds of a loop's health monitoring, plant seconds: a window from a minute to a day; an assessment at most
# every hour and at least every second (each costs a few ms of a worker's CPU).
HEALTH_WINDOW = (60.0, 86400.0)
HEALTH_EVERY = (1.0, 3600.0)


class HealthConfig(Strict):
    """A loop's health monitoring (docs/health.md, "Online"): while idle, its monitor's readings over the last
    ``window`` plant seconds are assessed every ``every`` plant seconds (``enabled`` false: never)."""

    enabled: bool = True
    window: Annotated[float, Field(ge=HEALTH_WINDOW[0], le=HEALTH_WINDOW[1])] = 3600.0
    every: Annotated[float, Field(ge=HEALTH_EVERY[0], le=HEALTH_EVERY[1])] = 60.0

    @model_validator(mode="after")
    def _within_window(self) -> HealthConfig:
        if self.every > self.window:
            raise ValueError(f"every ({self.every:g} s) must not exceed the window ({self.window:g} s)")
        return self


class LoopConfig(Strict):
    """One loop: a field link (``link`` + ``map``/``dbc``) or an in-process simulated plant (``sim``).

    ts: sample time of the experiment, plant seconds. speed: plant seconds per
    wall second — 1 for a real plant; more only for a simulated one (``sim``,
    or ``autotuner sim --speed`` behind a link). apply: write the tuned gains
    when a request does not say. group: loops of one exclusion group never
    tune at the same time. handshake: poll the device's TUNE/TBRK bits every
    ``handshake_poll`` wall seconds, so an HMI wired to the PLC starts and
    aborts tunings like the PIDAT block (docs/daemon.md, "PLC handshake").
    monitor_period: while the loop is idle, its mode, SP, MV, gains and PV
    are read this often, wall seconds (the live values of the status and the
    ``sample`` events). units: engineering units and display of its values
    (:class:`Units`; absent: no unit, 4 significant digits, axes fit the data).
    health: its health monitoring (:class:`HealthConfig`).
    """

    id: Annotated[str, Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")]
    description: str = ""
    link: str | None = None
    map: Path | None = None
    dbc: Path | None = None
    sim: SimPlant | None = None
    ts: PositiveFloat
    speed: Annotated[float, Field(gt=0.0, le=1000.0)] = 1.0
    tuning: Tuning = Tuning()
    limits: Limits = Limits()
    units: Units = Units()
    apply: bool = False
    group: str | None = None
    handshake: bool = False
    handshake_poll: Annotated[float, Field(ge=0.02, le=60.0)] = 0.5
    monitor_period: Annotated[float, Field(ge=0.05, le=60.0)] = 1.0
    health: HealthConfig = HealthConfig()

    @property
    def max_amp(self) -> float:
        """The largest relay amplitude of this loop, MV units (:func:`amp_bound`)."""
        return amp_bound(self.limits.mv, self.tuning.max_amp)

    @property
    def max_hysteresis(self) -> float:
        """The largest relay hysteresis of this loop, PV units (:func:`hysteresis_bound`)."""
        return hysteresis_bound(self.limits.pv, self.tuning.max_hysteresis)

    @model_validator(mode="after")
    def _amp_bounded(self) -> LoopConfig:
        if self.tuning.amp > self.max_amp:
            raise ValueError(f"tuning.amp {self.tuning.amp:g} is above the loop's largest relay amplitude "
                             f"{self.max_amp:g} (the span of limits.mv, else tuning.max_amp)")
        if self.tuning.hysteresis is not None and self.tuning.hysteresis > self.max_hysteresis:
            raise ValueError(f"tuning.hysteresis {self.tuning.hysteresis:g} is above the loop's largest hysteresis "
                             f"{self.max_hysteresis:g} (tuning.max_hysteresis, else a quarter of the span of "
                             "limits.pv)")
        return self

    @model_validator(mode="after")
    def _one_source(self) -> LoopConfig:
        if (self.link is None) == (self.sim is None):
            raise ValueError("give exactly one of 'link' (a field device URL) or 'sim' (a simulated plant)")
        if self.link is not None and not self.link.startswith(("modbus://", "modbus+tcp://", "modbus+rtu://",
                                                                 "can://")):
            raise ValueError(f"link {self.link!r} must be modbus://HOST:PORT[/UNIT], modbus+rtu://… or can://…")
        return self


Role = Literal["viewer", "operator", "admin"]


class Token(Strict):
    """An API token: who it is (``name``, recorded in the history), its role and the SHA-256 of the token (hex)."""

    name: str
    role: Role
    sha256: Annotated[str, Field(pattern=r"^[0-9a-fA-F]{64}$")]


# A stored OPC UA password hash (api/opcua/passwords.py): a password pasted in clear is refused.
PASSWORD_HASH_PATTERN = r"^scrypt\$\d+\$\d+\$\d+\$[A-Za-z0-9+/]+=*\$[A-Za-z0-9+/]+=*$"
SecurityPolicy = Literal["None", "Basic256Sha256_Sign", "Basic256Sha256_SignAndEncrypt"]
# The largest scrypt N a stored hash may use: 2^20 costs 1 GiB per login (autotuner password-hash uses 2^14, 16 MiB).
SCRYPT_MAX_N = 2**20


class OpcUaUser(Strict):
    """An OPC UA user: its name (recorded in the history as ``opcua:NAME``), its role (as the REST tokens') and
    the scrypt hash of its password (``autotuner password-hash``)."""

    name: Annotated[str, Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.@-]{0,63}$")]
    role: Role
    password_hash: Annotated[str, Field(pattern=PASSWORD_HASH_PATTERN)]

    @field_validator("password_hash")
    @classmethod
    def _scrypt_cost(cls, value: str) -> str:
        # At load, not at every login: a hash no login could ever match (or whose cost overflows scrypt).
        n, r, p = (int(x) for x in value.split("$")[1:4])
        if not (2 <= n <= SCRYPT_MAX_N and n & (n - 1) == 0 and 1 <= r <= 32 and 1 <= p <= 16):
            raise ValueError(f"scrypt parameters N={n}, r={r}, p={p} out of range (N a power of 2 up to 2^20, r 1-32, "
                             "p 1-16): make the hash with 'autotuner password-hash'")
        return value


class OpcUaConfig(Strict):
    """The OPC UA server beside the REST API (docs/opcua.md): where it listens, its security policies, its users.

    ``host`` None: the REST API's host. ``certificate``/``private_key``: the
    server's application certificate (DER or PEM) and key (PEM); both unset:
    generated on first start and kept beside the history (docs/opcua.md).
    ``trusted_clients``: a folder of trusted client certificates (DER or PEM,
    a CA's trusting what it signed); set, a session needs a trusted client
    certificate (so ``security`` must not offer None); unset, any is accepted.
    """

    host: str | None = None
    port: Annotated[int, Field(ge=1, le=65535)] = 4840
    security: Annotated[list[SecurityPolicy], Field(min_length=1)] = ["None", "Basic256Sha256_SignAndEncrypt"]
    certificate: Path | None = None
    private_key: Path | None = None
    trusted_clients: Path | None = None
    users: list[OpcUaUser] = []

    @model_validator(mode="after")
    def _pair(self) -> OpcUaConfig:
        if (self.certificate is None) != (self.private_key is None):
            raise ValueError("give both 'certificate' and 'private_key', or neither (then they are generated)")
        if "None" in self.security and "Basic256Sha256_SignAndEncrypt" not in self.security:
            raise ValueError("'security' offers None without Basic256Sha256_SignAndEncrypt: the passwords on the "
                             "None endpoint would travel in clear (they are encrypted with that policy)")
        if self.trusted_clients is not None and "None" in self.security:
            raise ValueError("'trusted_clients' needs 'security' without None: a client on the None policy has no "
                             "certificate to check")
        names = [user.name for user in self.users]
        if len(set(names)) != len(names):
            raise ValueError("a user name is used twice")
        return self


class HandBackConfig(Strict):
    """How the daemon hands loops back (docs/handback.md); wall seconds.

    window: one restore at the end of a session keeps trying this long before
    the loop is *not restored* (code 20). retry_first, retry_max: a loop not
    restored is tried again after ``retry_first``, the pause doubling up to
    ``retry_max``, for as long as the daemon runs. track_timeout: longest
    wait, per try, for the device's MV to read back the saved MV before AUTO
    is written. shutdown: SIGTERM/SIGINT hand every loop back within this
    bound (the process exits about ``shutdown + 5`` s after the signal at
    most). watchdog: the device's watchdog timeout while the daemon owns a
    loop (the heartbeat goes every 0.5 s); 0 does not arm it.
    """

    window: PositiveFloat = 30.0
    retry_first: PositiveFloat = 1.0
    retry_max: PositiveFloat = 60.0
    track_timeout: PositiveFloat = 5.0
    shutdown: PositiveFloat = 20.0
    watchdog: Annotated[float, Field(ge=0.0, le=3600.0)] = 10.0

    def session(self) -> HandBack:
        """The hand-back of one session under this config (its watchdog time in wall seconds)."""
        from autotuner.service.link_session import HandBack

        return HandBack(window=self.window, track_timeout=self.track_timeout, watchdog=self.watchdog)

    @model_validator(mode="after")
    def _ordered(self) -> HandBackConfig:
        if self.retry_first > self.retry_max:
            raise ValueError(f"retry_first ({self.retry_first:g}) must not exceed retry_max ({self.retry_max:g})")
        if 0.0 < self.watchdog <= 1.0:
            raise ValueError(f"watchdog must be 0 (off) or longer than the 0.5 s heartbeat twice, got {self.watchdog:g}")
        return self


class FleetConfig(Strict):
    """This daemon in a fleet sharing a PostgreSQL history (docs/fleet.md).

    name: its name among the daemons (default: host:port of its API).
    url: where the other daemons' clients reach its API (default:
    http://host:port as served). lease: how long a loop's lease holds
    without renewal, seconds — a dead daemon's loops are taken over after
    it. renew: how often the leases are renewed, seconds (default: a third
    of ``lease``). drain: start drained (serving no loop; for maintenance).
    """

    name: Annotated[str, Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.:@-]{0,127}$")] | None = None
    url: Annotated[str, Field(pattern=r"^https?://[^\s]+$", max_length=1000)] | None = None
    lease: Annotated[float, Field(ge=2.0, le=600.0)] = 10.0
    renew: Annotated[float, Field(gt=0.0, le=200.0)] | None = None
    drain: bool = False

    @model_validator(mode="after")
    def _renew_within_lease(self) -> FleetConfig:
        if self.renew is not None and self.renew > self.lease / 2:
            raise ValueError(f"renew ({self.renew:g} s) must be at most half the lease ({self.lease:g} s)")
        return self

    @property
    def renew_period(self) -> float:
        """How often the leases are renewed, seconds."""
        return self.lease / 3.0 if self.renew is None else self.renew


class DaemonConfig(Strict):
    """The whole file: the history database, the tokens, the loops and how they are handed back.

    ``history``: an SQLite file (relative to the config file), ``:memory:``,
    or an SQLAlchemy database URL such as ``postgresql+psycopg://user:pw@host/db``
    (the ``postgres`` extra installs the driver). ``opcua``: the OPC UA
    server's settings (None: no OPC UA server unless ``serve --opcua``).
    ``samplers``: processes the loops' sampling runs in, apart from the API
    (0: in the API's process, which clients can then slow down; docs/daemon.md,
    "A plant"). ``max_sessions``: most loops tuned at once; a TUNE beyond is
    refused (``overloaded``); None: as many as the samplers keep on time.
    ``sampler_load``: the share of a core a sampler may be predicted to need
    with a new session before that TUNE is refused (``overloaded``).
    ``fleet``: this daemon among others on one PostgreSQL history (a
    PostgreSQL history always holds leases; the section sets their name and
    times); not with an SQLite history. ``record_wait``: how long a session
    waits for the history to record what must be durable before it goes on
    (its saved state, a gains intent, its end, the restore), wall seconds
    (docs/handback.md).
    """

    history: str = "autotuner-history.db"
    tokens: list[Token] = []
    opcua: OpcUaConfig | None = None
    loops: list[LoopConfig]
    handback: HandBackConfig = HandBackConfig()
    samplers: Annotated[int, Field(ge=0, le=64)] = 1
    max_sessions: Annotated[int, Field(ge=1, le=100000)] | None = None
    sampler_load: Annotated[float, Field(gt=0.0, le=1.0)] = 0.6
    fleet: FleetConfig | None = None
    record_wait: Annotated[float, Field(ge=1.0, le=600.0)] = RECORD_WAIT

    @field_validator("history")
    @classmethod
    def _database(cls, history: str) -> str:
        if "://" in history:
            import sqlalchemy  # only here: the rest of the config does not need it

            try:
                sqlalchemy.engine.make_url(history)
            except (sqlalchemy.exc.ArgumentError, ValueError):
                # Not the URL itself: it may hold a password.
                raise ValueError("not a database URL (dialect+driver://user:password@host/database)") from None
        elif not history:
            raise ValueError("empty: give an SQLite file, ':memory:' or a database URL")
        return history

    @model_validator(mode="after")
    def _fleet_on_postgres(self) -> DaemonConfig:
        if self.fleet is not None and not self.history.startswith(("postgresql", "postgres")):
            raise ValueError("fleet: several daemons share a plant through a PostgreSQL history; this history is "
                             "not one (an SQLite history has one daemon)")
        return self

    @property
    def leased(self) -> bool:
        """The history is a PostgreSQL database: this daemon holds leases for the loops it serves."""
        return self.history.startswith(("postgresql", "postgres"))

    @model_validator(mode="after")
    def _unique_ids(self) -> DaemonConfig:
        seen: set[str] = set()
        for loop in self.loops:
            if loop.id in seen:
                raise ValueError(f"loop id {loop.id!r} is used twice")
            seen.add(loop.id)
        return self

    def loop(self, loop_id: str) -> LoopConfig | None:
        """The loop named ``loop_id``, or None."""
        return next((loop for loop in self.loops if loop.id == loop_id), None)


def _where(loc: tuple[Any, ...]) -> str:
    """``('loops', 1, 'tuning', 'amp')`` → ``loops[1].tuning.amp``."""
    text = ""
    for part in loc:
        text += f"[{part}]" if isinstance(part, int) else f".{part}" if text else str(part)
    return text or "(top level)"


def _message(error: dict[str, Any]) -> str:
    message = error["msg"]
    return re.sub(r"^(Value|Assertion) error, ", "", message)


def link_problem(loop: LoopConfig) -> tuple[str, str] | None:
    """Why ``loop``'s link cannot be opened as configured: (the field, the reason), or None when it can.

    The URL is parsed and the register map or DBC is loaded (paths already
    resolved), but nothing is connected: a device that is merely offline must
    not stop the daemon, while a URL or map that can never work must stop it
    at start, not fail every TUNE later.
    """
    if loop.link is None:
        return None
    from drivers.can_link import load_dbc
    from drivers.modbus_map import load_map

    from autotuner.service.remote_tuning import open_link

    can = loop.link.startswith("can://")
    if can and loop.map is not None:
        return "map", "a register map is for a Modbus link; a CAN link takes 'dbc'"
    if not can and loop.dbc is not None:
        return "dbc", "a DBC is for a CAN link; a Modbus link takes 'map'"
    try:
        if loop.map is not None:
            load_map(loop.map)
    except ValueError as exc:
        return "map", str(exc)
    try:
        if loop.dbc is not None:
            load_dbc(loop.dbc)
    except ValueError as exc:
        return "dbc", str(exc)
    try:
        open_link(loop.link, None if loop.map is None else str(loop.map), None if loop.dbc is None else str(loop.dbc))
    except ValueError as exc:
        return "link", str(exc)
    return None


def watchdog_problem(loop: LoopConfig, handback: HandBackConfig) -> tuple[str, str] | None:
    """Why the device watchdog cannot be armed on ``loop`` as configured (its CAN DBC cannot carry
    ``handback.watchdog`` × ``speed`` device seconds): (the field, the reason), or None."""
    if loop.link is None or not loop.link.startswith("can://") or handback.watchdog == 0.0:
        return None
    from drivers.can_link import load_dbc, watchdog_limit

    limit = watchdog_limit(load_dbc(loop.dbc))
    timeout = handback.watchdog * loop.speed
    if limit is None or timeout <= limit:
        return None
    return "speed", (f"handback.watchdog {handback.watchdog:g} s × speed {loop.speed:g} = {timeout:g} device seconds "
                     f"is more than the DBC's WdTime can carry ({limit:g} s): lower the watchdog or the speed")


def parse_config(data: Any, source: str) -> DaemonConfig:
    """Validate already-parsed YAML ``data``; errors name ``source`` and the path inside it."""
    try:
        return DaemonConfig.model_validate(data)
    except ValidationError as exc:
        lines = [f"{source}: {_where(e['loc'])}: {_message(e)}" for e in exc.errors()]
        raise ConfigError("\n".join(lines)) from None


class _UniqueKeys(yaml.SafeLoader):
    """YAML's safe loader, refusing a key given twice in one mapping (YAML would silently keep the last)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: dict[Any, int] = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            line = key_node.start_mark.line + 1
            if key in seen:
                raise ConfigError(f"{self.name}:{line}: key {key!r} given twice in one mapping (first on line "
                                  f"{seen[key]})")
            seen[key] = line
        return super().construct_mapping(node, deep)


def load_config(path: Path) -> DaemonConfig:
    """Read and validate the YAML file ``path``; relative paths in it become relative to its folder.

    Refused with a ConfigError: a file that cannot be read or is not UTF-8,
    YAML errors (with line and column), a key given twice, and everything
    :func:`parse_config` and :func:`link_problem` refuse.
    """
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset {exc.start}); "
                          "save the config as UTF-8") from None
    try:
        loader = _UniqueKeys(text)
        loader.name = str(path)
        try:
            data = loader.get_single_data()
        finally:
            loader.dispose()
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{path}:{mark.line + 1}:{mark.column + 1}" if mark is not None else str(path)
        raise ConfigError(f"{where}: not valid YAML: {getattr(exc, 'problem', None) or exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: (top level): must be a mapping with a 'loops' list")
    config = parse_config(data, str(path))
    base = path.parent

    def resolve(p: Path | None) -> Path | None:
        return None if p is None or p.is_absolute() else base / p

    loops = [loop.model_copy(update={"map": resolve(loop.map) or loop.map, "dbc": resolve(loop.dbc) or loop.dbc})
             for loop in config.loops]
    for i, loop in enumerate(loops):
        problem = link_problem(loop) or watchdog_problem(loop, config.handback)
        if problem is not None:
            raise ConfigError(f"{path}: loops[{i}].{problem[0]}: {problem[1]}")
    plain_file = config.history != ":memory:" and "://" not in config.history
    history = str(base / config.history) if plain_file else config.history
    opcua = config.opcua
    if opcua is not None:
        opcua = opcua.model_copy(update={key: resolve(getattr(opcua, key)) or getattr(opcua, key)
                                         for key in ("certificate", "private_key", "trusted_clients")})
        if opcua.trusted_clients is not None and not opcua.trusted_clients.is_dir():
            raise ConfigError(f"{path}: opcua.trusted_clients: {opcua.trusted_clients} is not a directory")
        for key in ("certificate", "private_key"):  # now, not as a failed start of the OPC UA server
            file = getattr(opcua, key)
            if file is not None and not file.is_file():
                raise ConfigError(f"{path}: opcua.{key}: {file} is not a file")
    return config.model_copy(update={"loops": loops, "history": history, "opcua": opcua})
