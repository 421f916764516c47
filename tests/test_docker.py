"""docker/Dockerfile: the variables each image sets configure what its entry point reads.

No Docker daemon is needed: the ENV blocks are read from the file and applied with the same
loader the commands use, so a renamed setting or a typo in the Dockerfile fails here."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

from sfmloc.builder_service.app import BuilderConfig
from sfmloc.config import env_overrides, load_config
from sfmloc.server.config import ServerConfig

DOCKERFILE = Path(__file__).resolve().parents[1] / "docker" / "Dockerfile"


def stage_env(stage: str) -> dict[str, str]:
    """The ENV variables set in one build stage (``FROM ... AS stage``)."""
    text = re.sub(r"\\\n", " ", DOCKERFILE.read_text())  # join continued lines
    env: dict[str, str] = {}
    current = None
    for line in text.splitlines():
        m = re.match(r"FROM\s+\S+\s+AS\s+(\w+)", line)
        if m:
            current = m.group(1)
        elif current == stage and line.startswith("ENV "):
            for item in shlex.split(line[4:], comments=True):
                key, _, value = item.partition("=")
                env[key] = value
    return env


def test_server_image_variables_configure_the_server():
    env = stage_env("server")
    for key, value in env.items():  # every variable names a setting (a typo is ignored silently)
        assert env_overrides(ServerConfig, "SFMLOC_", {key: value}), key
    c = load_config(ServerConfig, environ=env)
    assert c.maps == "/maps" and c.follow_builder
    assert c.grpc.address == "0.0.0.0:50051" and c.metrics_port == 9100
    assert c.zenoh.listen == ["tcp/0.0.0.0:7447"]
    text = DOCKERFILE.read_text()
    assert "EXPOSE 50051 7447 9100" in text and "environ['SFMLOC_GRPC__ADDRESS']" in text


def test_builder_image_variables_configure_the_builder():
    env = stage_env("builder")
    for key, value in env.items():
        assert env_overrides(BuilderConfig, "SFMLOC_BUILDER_", {key: value}), key
    c = load_config(BuilderConfig, prefix="SFMLOC_BUILDER_", environ=env)
    assert c.out == "/maps" and c.grpc == "0.0.0.0:50052"
    assert c.zenoh_listen == ["tcp/0.0.0.0:7448"]
    assert "environ['SFMLOC_BUILDER_GRPC']" in DOCKERFILE.read_text()


def test_dependencies_install_before_the_sources_are_copied():
    text = DOCKERFILE.read_text()
    assert text.index("pip install -r") < text.index("COPY service")
