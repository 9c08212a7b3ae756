"""Security on the wire with real processes on loopback.

The service runs with ``--zenoh-config FILE`` (JSON5) holding Zenoh's own TLS, mutual TLS,
user/password and access-control settings; its ``--listen`` flag replaces the file's endpoints.
A throw-away CA from ``trustme`` signs a server certificate for ``localhost`` and client
certificates whose common names are principals (``sim-0``: a robot, ``admin``).

* TLS: a client that trusts the CA gets answers (raw Zenoh, the ``shapeloc`` CLI); a plain TCP
  client and a TLS client without the CA are refused.
* Access control by user name (``usrpwd``) and by certificate common name (mutual TLS): a
  robot principal's scans and config under its own ``robots/<id>/`` reach the service and it
  gets its poses back (the simulator itself runs as that principal over mTLS), while its puts
  and deletes on ``maps/**`` and on another robot's config never reach the service: the maps
  an admin query returns are unchanged and no rejection is counted. An admin principal's puts
  and deletes on ``maps/**`` do reach it.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trustme
import zenoh

from schemas.codec import decode, encode
from schemas.messages import Health, Map, PoseMsg, RobotConfig, Scan
from service.adapters.convert import map_message_of
from sim_publisher.office import office_metric_map
from sim_publisher.scenario import make_setup

pytestmark = [pytest.mark.integration, pytest.mark.timeout(240)]

P = "shapeloc"
REPO = Path(__file__).resolve().parents[2]
ROBOT = "sim-0"  # the simulator's first robot id: the robot principal of these tests
ALL_MESSAGES = [
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


# --------------------------------------------------------------------------- helpers
@dataclass
class Certs:
    """PEM files of the test CA, the service's certificate and the principals' certificates."""

    ca: Path
    server: tuple[Path, Path]  # (certificate, private key)
    clients: dict[str, tuple[Path, Path]]


@pytest.fixture
def certs(tmp_path: Path) -> Certs:
    d = tmp_path / "pki"
    d.mkdir()
    ca = trustme.CA()
    ca.cert_pem.write_to_path(str(d / "ca.pem"))

    def issue(name: str, common_name: str) -> tuple[Path, Path]:
        cert = ca.issue_cert("localhost", "127.0.0.1", common_name=common_name)
        cert.cert_chain_pems[0].write_to_path(str(d / f"{name}.pem"))
        cert.private_key_pem.write_to_path(str(d / f"{name}.key"))
        return d / f"{name}.pem", d / f"{name}.key"

    server = issue("service", "shapeloc-service")
    clients = {p: issue(p, p) for p in (ROBOT, "admin")}
    return Certs(d / "ca.pem", server, clients)


def write_json5(path: Path, conf: dict[str, Any]) -> Path:
    """Write ``conf`` as a JSON5 file (a comment line first, so a JSON-only parser fails)."""
    path.write_text("// written by tests/integration/test_security.py\n" + json.dumps(conf))
    return path


def acl(subjects: dict[str, dict[str, list[str]]], robot_of: dict[str, str]) -> dict[str, Any]:
    """A default-deny access-control section of the service's config.

    ``subjects``: subject id -> match (``{"usernames": [...]}`` or
    ``{"cert_common_names": [...]}``); ``robot_of``: subject id -> the robot id it may act
    as; a subject not in ``robot_of`` is an admin (everything under the prefix, both ways).
    """
    rules: list[dict[str, Any]] = [
        {
            "id": "admin",
            "permission": "allow",
            "flows": ["ingress", "egress"],
            "messages": ALL_MESSAGES,
            "key_exprs": [f"{P}/**"],
        },
        {
            # what the service declares and sends: only key expressions, and data on the keys
            # the robot rules below let a robot subscribe to or query
            "id": "service-out",
            "permission": "allow",
            "flows": ["egress"],
            "messages": ["declare_subscriber", "declare_queryable", "liveliness_token"],
            "key_exprs": [f"{P}/**"],
        },
    ]
    policies: list[dict[str, Any]] = []
    for subject in subjects:
        robot = robot_of.get(subject)
        if robot is None:
            policies.append({"rules": ["admin"], "subjects": [subject]})
            continue
        own = f"{P}/robots/{robot}"
        reads = [f"{own}/pose", f"{P}/errors", f"{P}/service/health", f"{P}/maps/*"]
        rules += [
            {
                "id": f"{robot}-write",
                "permission": "allow",
                "flows": ["ingress"],
                "messages": ["put"],
                "key_exprs": [f"{own}/scan", f"{own}/config"],
            },
            {
                "id": f"{robot}-read",
                "permission": "allow",
                "flows": ["ingress"],
                "messages": ["declare_subscriber", "query"],
                # robots/*/pose too (the client library subscribes to a list of robots with
                # it): the egress rule below still delivers this robot's own poses only
                "key_exprs": [*reads, f"{P}/robots/*/pose"],
            },
            {
                "id": f"{robot}-answers",
                "permission": "allow",
                "flows": ["egress"],
                "messages": ["put", "reply"],
                "key_exprs": reads,
            },
            {
                "id": f"{robot}-alive",
                "permission": "allow",
                "flows": ["ingress"],
                "messages": ["declare_liveliness_subscriber", "liveliness_query"],
                "key_exprs": [f"{P}/service/alive/*"],
            },
        ]
        policies.append(
            {
                "rules": [f"{robot}-{r}" for r in ("write", "read", "answers", "alive")]
                + ["service-out"],
                "subjects": [subject],
            }
        )
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": [{"id": k, **v} for k, v in subjects.items()],
        "policies": policies,
    }


def tls_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def client_conf(endpoint: str, extra: dict[str, Any] | None = None) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    for k, v in (extra or {}).items():
        conf.insert_json5(k, json.dumps(v))
    return conf


def tls_extra(certs: Certs, principal: str | None = None) -> dict[str, Any]:
    extra: dict[str, Any] = {"transport/link/tls/root_ca_certificate": str(certs.ca)}
    if principal is not None:
        cert, key = certs.clients[principal]
        extra |= {
            "transport/link/tls/enable_mtls": True,
            "transport/link/tls/connect_certificate": str(cert),
            "transport/link/tls/connect_private_key": str(key),
        }
    return extra


def usr_extra(user: str, password: str) -> dict[str, Any]:
    return {"transport/auth/usrpwd/user": user, "transport/auth/usrpwd/password": password}


def refused(endpoint: str, extra: dict[str, Any] | None = None) -> bool:
    """Whether a client session to ``endpoint`` with ``extra`` cannot be opened."""
    try:
        s = zenoh.open(client_conf(endpoint, extra))
    except zenoh.ZError:
        return True
    s.close()
    return False


def health(s: zenoh.Session) -> Health | None:
    for r in s.get(f"{P}/service/health", timeout=2.0):
        if r.ok is not None:
            return decode(Health, r.ok.payload.to_bytes(), str(r.ok.encoding))
    return None


def stored_maps(s: zenoh.Session) -> dict[str, Map]:
    out = {}
    for r in s.get(f"{P}/maps/*", timeout=2.0):
        if r.ok is not None:
            m = decode(Map, r.ok.payload.to_bytes(), str(r.ok.encoding))
            out[m.map_id] = m
    return out


def wait_for(pred: Callable[[], bool], timeout_s: float, what: str, svc: Any) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}\n--- service log ---\n{svc.log()}")
        time.sleep(0.05)


def office_map(map_id: str = "office") -> Map:
    return map_message_of(replace(office_metric_map(), map_id=map_id))


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env.pop("RUST_LOG", None)
    return env


def run_module(*args: str, timeout_s: float = 120.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", *args],
        cwd=REPO,
        env=_env(),
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )


class Poses:
    """Poses of one robot received on a session."""

    def __init__(self, s: zenoh.Session, robot: str) -> None:
        self.got: list[PoseMsg] = []
        self._sub = s.declare_subscriber(
            f"{P}/robots/{robot}/pose",
            lambda smp: self.got.append(decode(PoseMsg, smp.payload.to_bytes())),
        )


def robot_attempts(s: zenoh.Session, other_robot: str) -> None:
    """What a robot principal must not be able to do: rewrite, add and delete maps, and
    configure another robot."""
    changed = Map(map_id="office", kind="metric", polylines=[[[0.0, 0.0], [1.0, 0.0]]])
    s.put(f"{P}/maps/office", encode(changed))
    s.put(f"{P}/maps/evil", encode(office_map("evil")))
    s.delete(f"{P}/maps/office")
    cfg = RobotConfig(map_id="office", method="icp", initial_pose=[9.4, 1.95, 0.0])
    s.put(f"{P}/robots/{other_robot}/config", encode(cfg))


def assert_nothing_reached(admin: zenoh.Session, before: dict[str, Map], robots: int) -> None:
    """The maps are as before and the service counted no map/config message at all (a
    rejected one would be counted under ``map.*`` / ``config.*``)."""
    time.sleep(1.0)  # the denied messages would have arrived by now
    assert stored_maps(admin) == before
    h = health(admin)
    assert h is not None and h.robots == robots and h.maps == len(before)
    assert not [k for k in (h.errors or {}) if k.startswith(("map.", "config."))], h.errors


# --------------------------------------------------------------------------- tests
def test_tls_listener_accepts_the_ca_and_refuses_plain_tcp(
    tmp_path: Path, certs: Certs, spawn_service: Callable[..., Any]
) -> None:
    port = tls_port()
    ep = f"tls/localhost:{port}"
    conf = write_json5(
        tmp_path / "service.json5",
        {
            "listen": {"endpoints": ["tcp/127.0.0.1:1"]},  # replaced by --listen
            "transport": {
                "link": {
                    "tls": {
                        "listen_certificate": str(certs.server[0]),
                        "listen_private_key": str(certs.server[1]),
                    }
                }
            },
        },
    )
    svc = spawn_service(
        tmp_path / "state", "--zenoh-config", str(conf), endpoint=ep, extra=tls_extra(certs)
    )
    assert "TLS listener" in svc.log() and f"'{ep}'" in svc.log()
    # a client with the CA: answered
    with zenoh.open(client_conf(ep, tls_extra(certs))) as s:
        h = health(s)
        assert h is not None and h.status == "ok"
    # plain TCP on the same port, and TLS without the test CA (WebPKI roots only): refused
    assert refused(f"tcp/localhost:{port}")
    assert refused(f"tcp/127.0.0.1:{port}")
    assert refused(ep)
    # the shapeloc CLI with --zenoh-config (its --connect replaces the file's endpoints)
    client_file = write_json5(
        tmp_path / "client.json5",
        {
            "connect": {"endpoints": ["tcp/127.0.0.1:1"]},
            "transport": {"link": {"tls": {"root_ca_certificate": str(certs.ca)}}},
        },
    )
    ok = run_module("clients", "--zenoh-config", str(client_file), "--connect", ep, "health")
    assert ok.returncode == 0, ok.stderr
    assert ok.stdout.startswith("ok: shapeloc"), ok.stdout
    plain = run_module("clients", "--connect", f"tcp/localhost:{port}", "health")
    assert plain.returncode == 1 and "cannot reach" in plain.stderr, plain.stderr


def test_access_control_by_user_name(
    tmp_path: Path, spawn_service: Callable[..., Any], open_session: Callable[..., Any]
) -> None:
    users = tmp_path / "users.txt"
    users.write_text(f"{ROBOT}:robot-secret\nadmin:admin-secret\n")
    conf = write_json5(
        tmp_path / "service.json5",
        {
            "transport": {"auth": {"usrpwd": {"dictionary_file": str(users)}}},
            "access_control": acl(
                {"robot": {"usernames": [ROBOT]}, "ops": {"usernames": ["admin"]}},
                {"robot": ROBOT},
            ),
        },
    )
    admin_x = usr_extra("admin", "admin-secret")
    svc = spawn_service(tmp_path / "state", "--zenoh-config", str(conf), extra=admin_x)
    assert "user/password dictionary" in svc.log() and "access control on" in svc.log()
    assert refused(svc.endpoint)  # no credentials
    assert refused(svc.endpoint, usr_extra(ROBOT, "wrong"))
    admin = open_session(svc.endpoint, admin_x)
    robot = open_session(svc.endpoint, usr_extra(ROBOT, "robot-secret"))

    admin.put(f"{P}/maps/office", encode(office_map()))
    wait_for(lambda: set(stored_maps(admin)) == {"office"}, 20.0, "admin's map", svc)
    before = stored_maps(admin)

    # the robot's own config and scans reach the service; its pose comes back
    setup = make_setup(1, seed=3, max_scans=40)
    poses = Poses(robot, ROBOT)
    cfg = RobotConfig(map_id="office", method="icp", initial_pose=list(setup.truth[0]))
    robot.put(f"{P}/robots/{ROBOT}/config", encode(cfg))
    wait_for(lambda: (h := health(robot)) is not None and h.robots == 1, 20.0, "config", svc)
    for k in range(3):
        robot.put(f"{P}/robots/{ROBOT}/scan", encode(scan_of(setup, k)))
        wait_for(lambda k=k: len(poses.got) == k + 1, 20.0, f"pose {k}", svc)
    assert [p.seq for p in poses.got] == [0, 1, 2]

    # its writes on maps/** and on another robot's config never reach the service
    robot_attempts(robot, "other")
    assert_nothing_reached(admin, before, robots=1)
    # the robot may read maps (a query), but gets the unchanged one
    assert stored_maps(robot) == before

    # another robot's poses are not delivered to this robot, even on a wildcard subscription
    seen: list[str] = []
    robot.declare_subscriber(
        f"{P}/robots/*/pose", lambda smp: seen.append(str(smp.key_expr).split("/")[-2])
    )
    other = Poses(admin, "other")
    admin.put(f"{P}/robots/other/config", encode(cfg))
    wait_for(lambda: (h := health(admin)) is not None and h.robots == 2, 20.0, "other", svc)
    admin.put(f"{P}/robots/other/scan", encode(scan_of(setup, 0)))
    robot.put(f"{P}/robots/{ROBOT}/scan", encode(scan_of(setup, 3)))
    wait_for(lambda: len(other.got) == 1 and len(poses.got) == 4, 20.0, "both poses", svc)
    time.sleep(0.5)
    assert seen == [ROBOT]

    # the admin's put and delete on maps/** do reach it
    admin.put(f"{P}/maps/second", encode(office_map("second")))
    wait_for(lambda: set(stored_maps(admin)) == {"office", "second"}, 20.0, "admin put", svc)
    admin.delete(f"{P}/maps/second")
    wait_for(lambda: set(stored_maps(admin)) == {"office"}, 20.0, "admin delete", svc)


def test_mutual_tls_access_by_certificate_name(
    tmp_path: Path, certs: Certs, spawn_service: Callable[..., Any]
) -> None:
    ep = f"tls/localhost:{tls_port()}"
    conf = write_json5(
        tmp_path / "service.json5",
        {
            "transport": {
                "link": {
                    "tls": {
                        "listen_certificate": str(certs.server[0]),
                        "listen_private_key": str(certs.server[1]),
                        "root_ca_certificate": str(certs.ca),
                        "enable_mtls": True,
                    }
                }
            },
            "access_control": acl(
                {"robot": {"cert_common_names": [ROBOT]}, "ops": {"cert_common_names": ["admin"]}},
                {"robot": ROBOT},
            ),
        },
    )
    svc = spawn_service(
        tmp_path / "state",
        "--zenoh-config",
        str(conf),
        endpoint=ep,
        extra=tls_extra(certs, "admin"),
    )
    assert "mutual TLS" in svc.log() and "no mutual TLS" not in svc.log()
    assert refused(ep, tls_extra(certs))  # the CA but no client certificate
    admin = zenoh.open(client_conf(ep, tls_extra(certs, "admin")))
    robot = zenoh.open(client_conf(ep, tls_extra(certs, ROBOT)))
    try:
        admin.put(f"{P}/maps/office", encode(office_map()))
        wait_for(lambda: set(stored_maps(admin)) == {"office"}, 20.0, "admin's map", svc)
        before = stored_maps(admin)

        # the simulator runs as the robot principal (its own certificate, mTLS): it configures
        # its robot and publishes scans; poses come back in lockstep (its truth key is denied)
        robot_file = write_json5(
            tmp_path / "robot.json5",
            {
                "mode": "client",
                "connect": {"endpoints": [ep]},
                "transport": {
                    "link": {
                        "tls": {
                            "root_ca_certificate": str(certs.ca),
                            "enable_mtls": True,
                            "connect_certificate": str(certs.clients[ROBOT][0]),
                            "connect_private_key": str(certs.clients[ROBOT][1]),
                        }
                    }
                },
            },
        )
        poses = Poses(admin, ROBOT)
        sim = run_module(
            "sim_publisher",
            "run",
            "--zenoh-config",
            str(robot_file),
            "--no-maps",
            "--robots",
            "1",
            "--method",
            "icp",
            "--scans",
            "5",
            "--max-rate",
            "--lockstep",
            "--wait-service",
            "20",
        )
        assert sim.returncode == 0, sim.stderr
        assert "lockstep: no pose" not in sim.stderr, sim.stderr
        wait_for(lambda: len(poses.got) >= 5, 10.0, "the simulator's poses", svc)
        assert sorted({p.seq for p in poses.got}) == [0, 1, 2, 3, 4]

        robot_attempts(robot, "other")
        assert_nothing_reached(admin, before, robots=1)

        admin.delete(f"{P}/maps/office")
        wait_for(lambda: stored_maps(admin) == {}, 20.0, "admin delete", svc)
    finally:
        robot.close()
        admin.close()


def scan_of(setup: Any, k: int) -> Scan:
    """Scan ``k`` (every tenth step of the tour) of a simulated setup as a wire message."""
    r, _a = setup.scan(10 * k)
    lz = setup.laser
    return Scan(
        seq=k,
        stamp=0.1 * k,
        angle_min=float(lz.angle_min),
        angle_increment=float(lz.angle_increment),
        range_min=0.0,
        range_max=float(lz.config.max_range),
        ranges=np.asarray(r, dtype=np.float64),
        odom=[float(v) for v in setup.odom[10 * k]],
    )


def test_client_config_file_is_the_base_and_flags_replace(tmp_path: Path) -> None:
    """clients.client.zenoh_config (the shapeloc CLI and shapeloc-sim): the file's values
    stay unless a flag replaces them; the default endpoint only fills a client's gap."""
    from clients.client import config_endpoints, zenoh_config
    from service.errors import InvalidMessage

    f = write_json5(
        tmp_path / "c.json5",
        {
            "mode": "peer",
            "connect": {"endpoints": ["tls/localhost:7001"]},
            "transport": {"auth": {"usrpwd": {"user": "u", "password": "p"}}},
        },
    )

    def as_dict(c: zenoh.Config) -> dict[str, Any]:
        return dict(json.loads(str(c)))

    kept = as_dict(zenoh_config(None, config_file=f, default_connect=["tcp/127.0.0.1:7447"]))
    assert kept["mode"] == "peer" and kept["connect"]["endpoints"] == ["tls/localhost:7001"]
    assert kept["transport"]["auth"]["usrpwd"]["user"] == "u"
    assert kept["scouting"]["multicast"]["enabled"] is False
    c = zenoh_config("client", connect=["tls/localhost:7002"], config_file=f)
    assert as_dict(c)["mode"] == "client"
    assert config_endpoints(c) == ["tls/localhost:7002"]  # replaced, not extended
    bare = write_json5(tmp_path / "bare.json5", {"mode": "client"})
    c = zenoh_config(None, config_file=bare, default_connect=["tcp/127.0.0.1:7447"])
    assert config_endpoints(c) == ["tcp/127.0.0.1:7447"]
    bad = tmp_path / "bad.json5"
    bad.write_text("{ not json5")
    with pytest.raises(InvalidMessage, match=r"bad\.json5"):
        zenoh_config(None, config_file=bad)
