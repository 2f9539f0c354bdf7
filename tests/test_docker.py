"""The compose files (docker/compose.yaml, docker/compose.fleet.yaml) and what they mount, checked without Docker.

Every daemon service's config loads as the daemon would read it (the file mounted at the path its
``--config`` names); its loops' links reach the compose file's plant (service, port, unit ids within
``--loops``, the same ``--speed``); a fleet's daemons share one PostgreSQL history — the compose file's
``postgres`` service, with its user, password and database — and have distinct names and URLs, each its
own service at the port it serves; no published port is used twice, in one file or across both (they
can run at once). The runs with a Docker engine are in docs/fleet.md, "In containers".
"""

from __future__ import annotations

import re
import shlex
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import pytest
import sqlalchemy
import yaml

from autotuner.service.config import DaemonConfig, load_config

ROOT = Path(__file__).parent.parent
DOCKER = ROOT / "docker"
COMPOSE_FILES = ("compose.yaml", "compose.fleet.yaml")


def compose(name: str) -> dict[str, Any]:
    """A compose file as YAML (safe_load resolves its ``<<: *anchor`` merges as compose does)."""
    return yaml.safe_load((DOCKER / name).read_text(encoding="utf-8"))


def option(command: list[str], name: str, default: str | None = None) -> str | None:
    """The value after ``name`` in a service's command, else ``default``."""
    return command[command.index(name) + 1] if name in command else default


@dataclass(frozen=True)
class Daemon:
    """A compose service that runs ``autotuner serve``: its name, its config as loaded from the mounted file,
    the port it serves inside the container and the host ports published to it."""

    service: str
    config: DaemonConfig
    port: int
    published: list[int]


def published_ports(service: dict[str, Any]) -> list[tuple[int, int]]:
    """(host port, container port) of every ``ports:`` entry of the short form HOST:CONTAINER."""
    pairs = []
    for entry in service.get("ports", []):
        parts = str(entry).split(":")  # [ADDRESS:]HOST:CONTAINER
        assert len(parts) >= 2, f"{entry}: publish with an explicit host port, so that clashes can be checked"
        pairs.append((int(parts[-2]), int(parts[-1])))
    return pairs


def daemons(name: str) -> list[Daemon]:
    """The daemon services of a compose file, each config loaded from the file mounted at its ``--config``."""
    found = []
    for service_name, service in compose(name)["services"].items():
        command = service.get("command", [])
        if command[:1] != ["serve"]:
            continue
        target = option(command, "--config")
        sources = [volume.split(":")[0] for volume in service.get("volumes", [])
                   if volume.split(":")[1] == target]
        assert len(sources) == 1, f"{name}: {service_name}: --config {target} is not mounted from one file"
        port = int(option(command, "--port", "8000"))
        published = [host for host, container in published_ports(service) if container == port]
        found.append(Daemon(service_name, load_config(DOCKER / sources[0]), port, published))
    return found


@dataclass(frozen=True)
class Plant:
    """A compose service that runs ``autotuner sim --modbus``: its name, Modbus port, loops and speed."""

    service: str
    port: int
    loops: int
    speed: float


def plants(name: str) -> dict[str, Plant]:
    found = {}
    for service_name, service in compose(name)["services"].items():
        command = service.get("command", [])
        if command[:1] == ["sim"]:
            host, port = option(command, "--modbus").rsplit(":", 1)
            assert host == "0.0.0.0", f"{service_name}: the plant must listen on the compose network"
            found[service_name] = Plant(service_name, int(port), int(option(command, "--loops", "1")),
                                        float(option(command, "--speed", "1")))
    return found


@pytest.mark.parametrize("name", COMPOSE_FILES)
def test_every_daemon_config_loads_and_its_loops_reach_the_plant(name):
    plant = plants(name)
    found = daemons(name)
    assert found, f"{name} runs no daemon"
    for daemon in found:
        assert daemon.config.loops, daemon.service
        units = set()
        for loop in daemon.config.loops:
            link = urlsplit(loop.link)
            assert link.scheme == "modbus", loop.id
            target = plant[link.hostname]  # a KeyError names a host that is no service of this file
            assert link.port == target.port, loop.id
            unit = int(link.path.strip("/"))
            assert 1 <= unit <= target.loops, f"{loop.id}: unit {unit} beyond the plant's --loops {target.loops}"
            units.add(unit)
            assert loop.speed == target.speed, f"{loop.id}: the loop's speed is not the plant's --speed"
        assert len(units) == len(daemon.config.loops), f"{daemon.service}: two loops on one unit"


@pytest.mark.parametrize("name", COMPOSE_FILES)
def test_every_daemon_takes_its_token_from_the_environment_and_may_raise_its_priority(name):
    services = compose(name)["services"]
    for daemon in daemons(name):
        service = services[daemon.service]
        assert service["environment"]["AUTOTUNER_TOKEN"].startswith("${AUTOTUNER_TOKEN:?")
        assert "SYS_NICE" in service["cap_add"]
        assert daemon.published, f"{daemon.service}: its API port {daemon.port} is not published"


def test_no_published_port_is_used_twice_in_either_file_or_across_both():
    ports = [host for name in COMPOSE_FILES for service in compose(name)["services"].values()
             for host, _ in published_ports(service)]
    assert ports and len(ports) == len(set(ports)), ports


def test_the_single_daemon_keeps_an_sqlite_history_on_its_volume():
    (daemon,) = daemons("compose.yaml")
    volumes = compose("compose.yaml")["services"][daemon.service]["volumes"]
    assert "history:/var/lib/autotuner" in volumes
    assert daemon.config.history.startswith("/var/lib/autotuner/") and not daemon.config.leased
    assert daemon.config.fleet is None


def test_the_fleet_daemons_share_one_postgres_history_with_distinct_names_and_urls():
    found = daemons("compose.fleet.yaml")
    assert len(found) == 2
    histories = {daemon.config.history for daemon in found}
    assert len(histories) == 1 and all(daemon.config.leased for daemon in found)
    names = [daemon.config.fleet.name for daemon in found]
    urls = [daemon.config.fleet.url for daemon in found]
    assert len(set(names)) == len(set(urls)) == 2, (names, urls)
    for daemon in found:  # the URL a redirect sends clients to: this service, at the port it serves
        assert daemon.config.fleet.url == f"http://{daemon.service}:{daemon.port}"
    a, b = (daemon.config.model_dump(exclude={"fleet"}) for daemon in found)
    assert a == b, "the fleet's daemon configs differ in more than their fleet sections"


def test_the_fleet_history_is_the_compose_files_postgres_service():
    services = compose("compose.fleet.yaml")["services"]
    url = sqlalchemy.engine.make_url(daemons("compose.fleet.yaml")[0].config.history)
    database = services[url.host]
    env = database["environment"]
    assert database["build"]["dockerfile"] == "docker/postgres.Dockerfile"
    assert (url.port or 5432) == 5432
    assert (url.username, url.password, url.database) == (
        env["POSTGRES_USER"], env["POSTGRES_PASSWORD"], env["POSTGRES_DB"])
    for daemon in daemons("compose.fleet.yaml"):  # started once the database and the plant answer
        depends = services[daemon.service]["depends_on"]
        assert depends[url.host] == {"condition": "service_healthy"}
        assert all(depends[plant] == {"condition": "service_healthy"} for plant in plants("compose.fleet.yaml"))


def copied_sources(dockerfile: Path) -> list[str]:
    """The build-context paths a Dockerfile's COPY instructions read."""
    sources = []
    for line in dockerfile.read_text(encoding="utf-8").splitlines():
        if line.startswith("COPY "):
            words = shlex.split(line)
            assert not any(word.startswith("--") for word in words), f"{line}: options not read here"
            sources += words[1:-1]
    return sources


@pytest.mark.parametrize("name", COMPOSE_FILES)
def test_every_image_builds_from_files_the_build_context_sends(name):
    allowed = [line[1:] for line in (ROOT / ".dockerignore").read_text(encoding="utf-8").splitlines()
               if line.startswith("!")]
    for service_name, service in compose(name)["services"].items():
        build = service["build"]
        assert (DOCKER / build["context"]).resolve() == ROOT.resolve(), service_name
        dockerfile = ROOT / build["dockerfile"]
        for source in copied_sources(dockerfile):
            assert (ROOT / source).exists(), f"{dockerfile.name}: COPY {source}: no such file"
            assert any(source == path or source.startswith(path + "/") for path in allowed), (
                f"{dockerfile.name}: COPY {source}: left out of the build context by .dockerignore")


@pytest.mark.parametrize("script", ["entrypoint.sh", "postgres-entrypoint.sh"])
def test_the_entrypoints_are_executable_posix_shell(script):
    path = DOCKER / script
    assert path.stat().st_mode & 0o111
    assert path.read_text(encoding="utf-8").startswith("#!/bin/sh\n")
    checked = subprocess.run(["sh", "-n", str(path)], capture_output=True, text=True)
    assert checked.returncode == 0, checked.stderr
    assert re.search(r"^exec ", path.read_text(encoding="utf-8"), re.MULTILINE), "PID 1 must be the server itself"
