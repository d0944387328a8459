"""The TLS + access-control profile (deploy/router-tls.json5, services/tools/security.py)
against a real router: an in-process Python router with the generated configuration, and
client sessions holding certificates issued here, in tmp_path, by a throw-away CA (the
``openssl`` command line; no Python crypto package needed).

"Not delivered" is checked event-based: the forbidden put goes first, then an allowed
marker that takes the same path (same sender, or a sender that started after the router had
handled the forbidden put; same receiving subscriber). Once the marker has arrived, anything
routed before it would have: samples of one subscriber on one link arrive in order (samples
of two subscribers of one session were seen to overtake each other, hence "same subscriber").
"""

from __future__ import annotations

import json
import shutil
import subprocess
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import json5
import pytest
import zenoh
from support import closed_at_exit

from services.cli import main as cli_main
from services.runtime.config import RuntimeConfig, load_config, zenoh_config
from services.runtime.delivery import (
    DeliverySettings,
    OutboxSettings,
    ReliablePublisher,
    ReliableSubscription,
)
from services.runtime.service import ServiceRuntime
from services.tools import security

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs openssl")

TIMEOUT_S = 5.0
CONNECT_TIMEOUT_MS = 1000  # a refused client gives up after this, instead of retrying
TRAINS = ("T1", "T2")
ROLES = ("gateway-T1", "ingestion", "extraction", "calibration", "filtering", "viewer")


class CertificateAuthority:
    """A CA in ``directory``; :meth:`issue` signs an EC P-256 certificate for a name."""

    def __init__(self, directory: Path, name: str = "trackfusion-test-ca") -> None:
        directory.mkdir(parents=True, exist_ok=True)
        self.dir = directory
        self.cert = directory / "ca.pem"
        self.key = directory / "ca-key.pem"
        _genkey(self.key)
        _openssl(
            "req", "-x509", "-new", "-key", self.key, "-out", self.cert, "-days", "2",
            "-subj", f"/CN={name}",
            "-addext", "basicConstraints=critical,CA:TRUE",
            "-addext", "keyUsage=critical,keyCertSign,cRLSign",
        )  # fmt: skip

    def issue(self, common_name: str, san: str | None = None) -> tuple[Path, Path]:
        """``(certificate, key)`` for ``common_name``, valid for client and server use."""
        cert, key, csr = (self.dir / f"{common_name}{s}" for s in (".pem", "-key.pem", ".csr"))
        ext = self.dir / f"{common_name}.ext"
        ext.write_text(
            "basicConstraints=critical,CA:FALSE\n"
            "keyUsage=critical,digitalSignature\n"
            "extendedKeyUsage=serverAuth,clientAuth\n"
            f"subjectAltName={san or 'DNS:' + common_name}\n"
        )
        _genkey(key)
        _openssl("req", "-new", "-key", key, "-out", csr, "-subj", f"/CN={common_name}")
        _openssl(
            "x509", "-req", "-in", csr, "-CA", self.cert, "-CAkey", self.key,
            "-CAcreateserial", "-out", cert, "-days", "2", "-extfile", ext,
        )  # fmt: skip
        return cert, key


def _openssl(*args: object) -> None:
    result = subprocess.run(
        ["openssl", *map(str, args)], capture_output=True, text=True, timeout=30, check=False
    )
    assert result.returncode == 0, f"openssl {args[0]} failed: {result.stderr}"


def _genkey(path: Path) -> None:
    _openssl("genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256", "-out", path)


@pytest.fixture
def ca(tmp_path: Path) -> CertificateAuthority:
    return CertificateAuthority(tmp_path / "certs")


@pytest.fixture
def tls_router(
    ca: CertificateAuthority, free_port: int, namespace: str
) -> Iterator[dict[str, str]]:
    """The generated profile for fleet T1, T2 in an in-process router on 127.0.0.1;
    yields ``{"endpoint": …, "ca": …}``."""
    endpoint = f"tls/127.0.0.1:{free_port}"
    cert, key = ca.issue("router", san="DNS:localhost,IP:127.0.0.1")
    settings = security.router_acl_config(namespace, TRAINS, endpoint, ca.cert, cert, key)
    settings["scouting"]["delay"] = 0  # nothing to scout: open at once
    session = zenoh.open(zenoh_config(settings))
    try:
        yield {"endpoint": endpoint, "ca": str(ca.cert)}
    finally:
        session.close()


def client_settings(
    router: dict[str, str], cert: Path | None = None, key: Path | None = None
) -> dict[str, object]:
    """What deploy/service-tls.json5 says, for this router and these credentials."""
    tls: dict[str, object] = {"root_ca_certificate": router["ca"]}
    if cert is not None:
        tls |= {"connect_certificate": str(cert), "connect_private_key": str(key)}
        tls["enable_mtls"] = True
    return {
        "mode": "client",
        "connect": {"endpoints": [router["endpoint"]], "timeout_ms": CONNECT_TIMEOUT_MS},
        "transport": {"link": {"tls": tls}},
    }


@pytest.fixture
def open_as(
    ca: CertificateAuthority, tls_router: dict[str, str]
) -> Iterator[Callable[[str], zenoh.Session]]:
    """``open_as(common_name)``: a client session with a certificate for that name."""

    def open_(common_name: str) -> zenoh.Session:
        cert, key = ca.issue(common_name)
        return zenoh.open(zenoh_config(client_settings(tls_router, cert, key)))

    with closed_at_exit(open_) as opened:
        yield opened


class Keys:
    """Collect the key expressions of the samples a subscriber receives; wait for one."""

    def __init__(self) -> None:
        self.seen: list[str] = []
        self._cond = threading.Condition()

    def __call__(self, sample: zenoh.Sample | str) -> None:
        with self._cond:
            self.seen.append(str(getattr(sample, "key_expr", sample)))
            self._cond.notify_all()

    def wait_for(self, key: str, timeout: float = TIMEOUT_S) -> None:
        with self._cond:
            assert self._cond.wait_for(lambda: key in self.seen, timeout), (
                f"{key} not received within {timeout} s; got {self.seen}"
            )


def subscribe(session: zenoh.Session, *keyexprs: str) -> Keys:
    keys = Keys()
    for keyexpr in keyexprs:
        session.declare_subscriber(keyexpr, keys)  # undeclared when the session closes
    return keys


def wait_matched(publisher: zenoh.Publisher, timeout: float = TIMEOUT_S) -> None:
    """Wait until the router has told ``publisher`` of a matching subscriber."""
    matched = threading.Event()
    listener = publisher.declare_matching_listener(lambda s: s.matching and matched.set())
    try:
        if not publisher.matching_status.matching:
            assert matched.wait(timeout), f"no subscriber matched {publisher.key_expr}"
    finally:
        listener.undeclare()


# --- the generator ---------------------------------------------------------------------------


def test_deploy_profile_is_the_generator_output_for_the_example_fleet() -> None:
    text = (Path(__file__).resolve().parents[2] / "deploy" / "router-tls.json5").read_text()
    certs = Path("/etc/trackfusion/certs")
    expected = security.router_acl_config(
        "tf",
        ["T001", "T002", "T003", "T004"],
        security.DEFAULT_LISTEN,
        certs / "ca.pem",
        certs / "router.pem",
        certs / "router-key.pem",
    )
    assert json5.loads(text) == expected, "regenerate deploy/router-tls.json5 (see its header)"
    zenoh_config(expected)  # a valid Zenoh configuration


def test_secure_config_command_prints_the_profile(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["secure-config", "--trains", "A1,B2", "--ns", "net", "--certs", "/c"]
    assert cli_main(argv) == 0
    config = json5.loads(capsys.readouterr().out)
    assert config["listen"]["endpoints"] == ["tls/0.0.0.0:7447"]
    assert config["transport"]["link"]["tls"]["enable_mtls"] is True
    assert config["transport"]["link"]["tls"]["root_ca_certificate"] == "/c/ca.pem"
    acl = config["access_control"]
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    rules = {r["id"]: r for r in acl["rules"]}
    assert rules["gateway-B2:put"]["key_exprs"] == ["net/gps/B2", "net/raw/B2/**"]
    assert rules["gateway-B2:put"]["flows"] == ["ingress"]
    assert {s["id"]: s["cert_common_names"] for s in acl["subjects"]}["gateway-A1"] == [
        "gateway-A1"
    ]
    assert not any("delete" in r["messages"] for r in acl["rules"])


def test_secure_config_refuses_a_plain_tcp_listener() -> None:
    with pytest.raises(SystemExit, match="tls/"):
        cli_main(["secure-config", "--trains", "T1", "--certs", "/c", "--listen", "tcp/[::]:1"])


# --- against a router ------------------------------------------------------------------------


def test_gateway_publishes_only_under_its_own_raw_and_gps_keys(
    open_as: Callable[[str], zenoh.Session], namespace: str
) -> None:
    ns = namespace
    ingestion = subscribe(open_as("ingestion"), f"{ns}/raw/**")
    gps = subscribe(open_as("ingestion"), f"{ns}/gps/*")
    viewer = subscribe(open_as("viewer"), f"{ns}/trc/**")
    gateway = open_as("gateway-T1")
    trc_import = open_as("trc-import").declare_publisher(f"{ns}/trc/L0/marker")
    wait_matched(trc_import)

    own_raw = gateway.declare_publisher(f"{ns}/raw/T1/u0")
    other_raw = gateway.declare_publisher(f"{ns}/raw/T2/u0")
    wait_matched(own_raw)
    # The gateway is told of ingestion's raw/** subscriber, so it does send raw/T2/u0:
    # what keeps it from ingestion is the router's ingress rule.
    wait_matched(other_raw)

    other_raw.put(b"forbidden: another train")
    gateway.put(f"{ns}/trc/L1/s1", b"forbidden: not a gateway key")
    own_raw.put(b"allowed")
    gateway.put(f"{ns}/gps/T1", b"allowed marker")

    ingestion.wait_for(f"{ns}/raw/T1/u0")  # the router has handled the gateway's puts
    gps.wait_for(f"{ns}/gps/T1")
    trc_import.put(b"allowed marker")  # routed after the gateway's trc put, if it was
    viewer.wait_for(f"{ns}/trc/L0/marker")
    assert ingestion.seen == [f"{ns}/raw/T1/u0"]
    assert viewer.seen == [f"{ns}/trc/L0/marker"]
    for publisher in (other_raw, own_raw, trc_import):
        publisher.undeclare()


def test_client_without_certificate_is_refused(
    ca: CertificateAuthority, tls_router: dict[str, str], tmp_path: Path
) -> None:
    with pytest.raises(zenoh.ZError):
        zenoh.open(zenoh_config(client_settings(tls_router))).close()
    # A certificate from another CA is no better.
    stranger = CertificateAuthority(tmp_path / "other-ca").issue("gateway-T1")
    with pytest.raises(zenoh.ZError):
        zenoh.open(zenoh_config(client_settings(tls_router, *stranger))).close()
    # Still serving the legitimate ones.
    cert, key = ca.issue("viewer")
    zenoh.open(zenoh_config(client_settings(tls_router, cert, key))).close()


def test_unknown_common_name_may_do_nothing(
    open_as: Callable[[str], zenoh.Session], namespace: str
) -> None:
    """A certificate of the CA whose name no policy knows: it connects, but default deny."""
    ns = namespace
    viewer = subscribe(open_as("viewer"), f"{ns}/index/**")
    stranger = open_as("contractor-laptop")
    forbidden = stranger.declare_publisher(f"{ns}/index/L1/s1")
    extraction = open_as("extraction").declare_publisher(f"{ns}/index/L1/s2")
    wait_matched(extraction)  # the router knows the viewer's subscriber now…
    assert not forbidden.matching_status.matching  # …and does not tell the stranger
    stranger_sees = subscribe(stranger, f"{ns}/index/**")
    extraction.put(b"allowed")
    viewer.wait_for(f"{ns}/index/L1/s2")  # routed to every allowed subscriber at once
    assert stranger_sees.seen == []  # refused: its subscription was never declared
    forbidden.undeclare()
    extraction.undeclare()


def test_service_cannot_publish_or_subscribe_outside_its_keys(
    open_as: Callable[[str], zenoh.Session], namespace: str
) -> None:
    ns = namespace
    viewer = subscribe(open_as("viewer"), f"{ns}/trc/**")
    indices = subscribe(open_as("viewer"), f"{ns}/index/**")
    extraction_session = open_as("extraction")
    extraction = subscribe(extraction_session, f"{ns}/raw/**", f"{ns}/accel/**")
    ingestion_session = open_as("ingestion")
    ingestion = subscribe(ingestion_session, f"{ns}/raw/**")
    gateway = open_as("gateway-T1")
    trc_import = open_as("trc-import").declare_publisher(f"{ns}/trc/L0/marker")
    wait_matched(trc_import)

    # Extraction may put index/**, not trc/**.
    extraction_session.put(f"{ns}/trc/L1/s1", b"forbidden")
    extraction_session.put(f"{ns}/index/L1/s1", b"allowed")
    indices.wait_for(f"{ns}/index/L1/s1")  # the router has handled the trc put
    trc_import.put(b"allowed marker")
    viewer.wait_for(f"{ns}/trc/L0/marker")
    assert viewer.seen == [f"{ns}/trc/L0/marker"]

    # Extraction may not subscribe to raw/**: a raw chunk that reached ingestion was routed
    # before ingestion's accel reply, so it would normally reach extraction first. (Two
    # subscribers of one session may see their samples reordered, so this check could miss
    # a leak; it cannot fail spuriously.)
    raw = gateway.declare_publisher(f"{ns}/raw/T1/u0")
    wait_matched(raw)
    raw.put(b"raw")
    ingestion.wait_for(f"{ns}/raw/T1/u0")
    accel = ingestion_session.declare_publisher(f"{ns}/accel/T1/u0")
    wait_matched(accel)
    accel.put(b"accel")
    extraction.wait_for(f"{ns}/accel/T1/u0")
    assert extraction.seen == [f"{ns}/accel/T1/u0"]
    for publisher in (raw, accel, trc_import):
        publisher.undeclare()


def test_queries_reach_only_the_services_allowed_to_ask(
    open_as: Callable[[str], zenoh.Session], namespace: str
) -> None:
    ns = namespace
    calibration = open_as("calibration")
    answered = threading.Event()

    def on_query(query: zenoh.Query) -> None:
        query.reply(f"{ns}/model/calibration", b"model v1")
        answered.set()

    queryable = calibration.declare_queryable(f"{ns}/model/**", on_query)
    filtering = open_as("filtering")
    replies = [r.ok.key_expr for r in filtering.get(f"{ns}/model/**", timeout=TIMEOUT_S) if r.ok]
    assert [str(k) for k in replies] == [f"{ns}/model/calibration"]

    # The viewer has no business asking for models: no reply, and the query never arrives.
    answered.clear()
    viewer = open_as("viewer")
    assert [r for r in viewer.get(f"{ns}/model/**", timeout=1.0) if r.ok] == []
    assert not answered.is_set()
    queryable.undeclare()

    # `import-trc` asks filtering's states whether it holds its records.
    states = filtering.declare_queryable(
        f"{ns}/q/state/**", lambda query: query.reply(f"{ns}/q/state/L1/s1", b"state")
    )
    trc_import = open_as("trc-import")
    replies = [
        r.ok.key_expr for r in trc_import.get(f"{ns}/q/state/L1/s1", timeout=TIMEOUT_S) if r.ok
    ]
    assert [str(k) for k in replies] == [f"{ns}/q/state/L1/s1"]
    states.undeclare()


def test_a_service_runtime_works_under_the_profile(
    ca: CertificateAuthority,
    tls_router: dict[str, str],
    open_as: Callable[[str], zenoh.Session],
    namespace: str,
) -> None:
    """ServiceRuntime's own traffic (dead letters, liveliness token, the flush before close)
    is allowed for its role, and an operator sees the token."""
    cert, key = ca.issue("extraction")
    conf = RuntimeConfig(ns=namespace, instance="sec", zenoh=client_settings(tls_router, cert, key))
    watcher = open_as("viewer")
    letters = subscribe(open_as("operator"), f"{namespace}/deadletter/**")
    with ServiceRuntime("extraction", conf, connect_timeout=TIMEOUT_S) as rt:
        rt.announce()
        operator = open_as("operator")
        alive = [
            str(r.ok.key_expr)
            for r in operator.liveliness().get(f"{namespace}/alive/**", timeout=TIMEOUT_S)
            if r.ok
        ]
        assert alive == [f"{namespace}/alive/extraction/sec"]
        wait_matched(rt.deadletters.publisher)
        rt.deadletters.reject(f"{namespace}/accel/T1/u0", "test reason", b"junk")
        letters.wait_for(f"{namespace}/deadletter/extraction")
        # The viewer may not watch liveliness.
        assert [r for r in watcher.liveliness().get(f"{namespace}/alive/**", timeout=1.0)] == []


def test_at_least_once_delivery_works_under_the_profile(
    open_as: Callable[[str], zenoh.Session], namespace: str, tmp_path: Path
) -> None:
    """Outbox queries and their replies are allowed inside a role's own keys: filtering
    gets the indices and models published before it subscribed; the viewer, which may not
    read models, gets none of calibration's models, even asking for every key."""
    ns = namespace
    settings = DeliverySettings(replay_s=0.5, outbox=OutboxSettings(dir=str(tmp_path)))
    extraction = ReliablePublisher.open(open_as("extraction"), ns, "extraction", "a", settings)
    models = ReliablePublisher.open(open_as("calibration"), ns, "calibration", "a", settings)
    published = [f"{ns}/index/L1/s{i}" for i in range(3)]
    for key in published:
        extraction.put(key, b"index")
    models.put(f"{ns}/model/calibration", b"model v1")
    assert extraction.flush(TIMEOUT_S) and models.flush(TIMEOUT_S)

    def replaying(session: zenoh.Session, got: Keys, *kinds: str) -> ReliableSubscription:
        subscriptions = {kind: f"{ns}/{kind}/**" for kind in kinds}
        return ReliableSubscription(
            session, ns, subscriptions, lambda _kind, key, _payload: got(key),
            lambda producer, epoch, head: subscription_marks.append((producer, epoch, head)),
            settings=settings,
        )  # fmt: skip

    subscription_marks: list[tuple[str, str, int]] = []
    got = Keys()
    subscriptions = [replaying(open_as("filtering"), got, "index", "model")]
    for key in (*published, f"{ns}/model/calibration"):
        got.wait_for(key)
    nosy = Keys()
    subscriptions.append(replaying(open_as("viewer"), nosy, "model", "index"))
    nosy.wait_for(published[0])  # the viewer may read indices, so their replay arrives…
    assert not any("/model/" in key for key in nosy.seen)  # …but never a model
    for subscription in subscriptions:
        subscription.undeclare()
    extraction.undeclare()
    models.undeclare()


def test_profile_is_json_serialisable_for_any_fleet() -> None:
    config = security.router_acl_config("tf", [], "tls/[::]:7447", "ca", "c", "k")
    policies = {p["id"] for p in config["access_control"]["policies"]}
    assert policies == set(security.ROLES)
    json.dumps(config)
    with pytest.raises(ValueError, match="tls/"):
        security.router_acl_config("tf", ["T1"], "tcp/[::]:7447", "ca", "c", "k")


def test_deploy_service_profile_connects_with_its_paths_replaced(
    ca: CertificateAuthority, tls_router: dict[str, str], namespace: str
) -> None:
    """deploy/service-tls.json5 is a working client profile once its paths point here."""
    conf = load_config(Path(__file__).resolve().parents[2] / "deploy" / "service-tls.json5")
    cert, key = ca.issue("filtering")
    settings = json.loads(json.dumps(conf.zenoh))
    settings["connect"]["endpoints"] = [tls_router["endpoint"]]
    settings["transport"]["link"]["tls"] |= {
        "root_ca_certificate": tls_router["ca"],
        "connect_certificate": str(cert),
        "connect_private_key": str(key),
    }
    service = RuntimeConfig(ns=namespace, instance="sec", zenoh=settings)
    with ServiceRuntime("filtering", service, connect_timeout=TIMEOUT_S) as rt:
        rt.announce()
