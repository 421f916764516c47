"""Zenoh access control for a fleet of devices: each device may publish frames and read poses
only under its own client id (issue 12).

The server enforces it: its Zenoh configuration holds an ``access_control`` section (zenoh's
own ACL, checked by the server's Zenoh runtime on every message to and from each connected
instance) whose subjects are devices identified by their TLS client certificate's common name
(mutual TLS, ``cert_common_names``) or by a Zenoh user name (``transport/auth/usrpwd``,
``usernames``). Default: deny. Per device ``D``, on any map:

- ingress ``put`` on ``sfmloc/*/D/frame`` and ``sfmloc/*/D/frame/*`` (its frames, to any
  server or addressed to one);
- ingress ``declare_subscriber`` on ``sfmloc/*/D/pose`` and egress ``put`` on it (its poses);

and for every device: the server's own subscriptions ``sfmloc/*/*/frame`` and ``.../frame/*``
(frames addressed to it) may be declared to it
(egress ``declare_subscriber``; without it a device routes no frame to the server: a rule for
``sfmloc/*/D/frame`` alone does not let the wider declaration out, measured with zenoh 1.10),
and discovery (the server's liveliness token and info queryable under ``sfmloc/servers/**``).
Admin subjects (operators, the builder) may do anything under ``sfmloc/**``.

Devices must connect in Zenoh ``client`` mode: peers would also connect to one another
(gossip) and exchange frames directly, where the server's rules cannot see them.

``sfmloc auth zenoh-acl`` writes such a configuration; ``docker/zenoh-server-acl.json5`` is one
for two devices (tested in tests/test_zenoh_acl.py with real sessions).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any, Literal

from sfmloc_client.keys import ROOT, check_name

from ..errors import ConfigError

Identify = Literal["cert", "user"]

_DISCOVERY = f"{ROOT}/servers/**"
_SERVER_INFO = f"{ROOT}/servers/*/info"


def _rule(rid: str, flow: str, messages: list[str], key_exprs: list[str]) -> dict[str, Any]:
    return {
        "id": rid,
        "permission": "allow",
        "flows": [flow],
        "messages": messages,
        "key_exprs": key_exprs,
    }


def _subject(sid: str, name: str, identify: Identify) -> dict[str, Any]:
    field = "cert_common_names" if identify == "cert" else "usernames"
    return {"id": sid, field: [name]}


def acl_section(
    devices: Sequence[str], admins: Sequence[str] = (), identify: Identify = "cert"
) -> dict[str, Any]:
    """The ``access_control`` section for ``devices`` (client ids, each also its certificate
    common name or Zenoh user name) and ``admins`` (names with every right under sfmloc/**)."""
    if identify not in ("cert", "user"):
        raise ConfigError(f"identify must be 'cert' or 'user', got {identify!r}")
    if not devices and not admins:
        raise ConfigError("an access control list needs at least one device or admin")
    names = list(devices) + list(admins)
    if len(set(names)) != len(names):
        raise ConfigError("each device and admin name may appear once")
    for d in names:
        check_name(d, "device name")  # it is a key expression chunk: no '*', '/', '$'
    rules = [
        _rule(
            "server-frame-subscription",
            "egress",
            ["declare_subscriber"],
            [f"{ROOT}/*/*/frame", f"{ROOT}/*/*/frame/*"],  # frames to any server / to this one
        ),
        _rule(
            "discovery-in",
            "ingress",
            ["liveliness_query", "declare_liveliness_subscriber", "query"],
            [_DISCOVERY],
        ),
        _rule(
            "discovery-out",
            "egress",
            ["liveliness_token", "declare_queryable", "reply"],
            [_DISCOVERY, _SERVER_INFO],
        ),
    ]
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    common = [r["id"] for r in rules]
    for d in devices:
        own = [
            _rule(
                f"{d}/frames-in",
                "ingress",
                ["put"],
                [f"{ROOT}/*/{d}/frame", f"{ROOT}/*/{d}/frame/*"],
            ),
            _rule(
                f"{d}/poses-subscribe", "ingress", ["declare_subscriber"], [f"{ROOT}/*/{d}/pose"]
            ),
            _rule(f"{d}/poses-out", "egress", ["put"], [f"{ROOT}/*/{d}/pose"]),
        ]
        rules += own
        subjects.append(_subject(f"device/{d}", d, identify))
        policies.append({"rules": common + [r["id"] for r in own], "subjects": [f"device/{d}"]})
    if admins:
        every = [
            "put",
            "delete",
            "declare_subscriber",
            "query",
            "declare_queryable",
            "reply",
            "liveliness_token",
            "declare_liveliness_subscriber",
            "liveliness_query",
        ]
        rules.append(_rule("admin-in", "ingress", every, [f"{ROOT}/**"]))
        rules.append(_rule("admin-out", "egress", every, [f"{ROOT}/**"]))
        for a in admins:
            subjects.append(_subject(f"admin/{a}", a, identify))
        policies.append(
            {"rules": ["admin-in", "admin-out"], "subjects": [f"admin/{a}" for a in admins]}
        )
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def server_config(
    devices: Sequence[str],
    admins: Sequence[str] = (),
    identify: Identify = "cert",
    listen: str = "tls/0.0.0.0:7447",
    tls_ca: str = "/certs/ca.pem",
    tls_cert: str = "/certs/server.pem",
    tls_key: str = "/certs/server.key",
    users_file: str = "/certs/zenoh-users.txt",
) -> dict[str, Any]:
    """A whole server-side Zenoh configuration (``sfmloc serve --zenoh-config FILE``): TLS on
    ``listen`` (mutual TLS when devices are identified by certificate), the user dictionary
    when by user name, no multicast scouting, and the access control section."""
    tls: dict[str, Any] = {
        "root_ca_certificate": tls_ca,
        "listen_certificate": tls_cert,
        "listen_private_key": tls_key,
        "enable_mtls": identify == "cert",
    }
    conf: dict[str, Any] = {
        "mode": "peer",
        "listen": {"endpoints": [listen]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"link": {"tls": tls}},
        "access_control": acl_section(devices, admins, identify),
    }
    if identify == "user":
        conf["transport"]["auth"] = {"usrpwd": {"dictionary_file": users_file}}
    return conf


def render(conf: dict[str, Any], header: str = "") -> str:
    """JSON5 text of a configuration (plain JSON, which JSON5 reads), after ``//`` comments."""
    lines = [f"// {ln}".rstrip() for ln in header.splitlines()]
    return "\n".join([*lines, json.dumps(conf, indent=2), ""])
