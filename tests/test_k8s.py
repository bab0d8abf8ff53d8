"""deploy/k8s/ and docker-compose.yml describe the same services.

Both are parsed as YAML (no cluster, no Docker needed) and compared: the same image, the
same commands, container ports and environment, health checks through the same
deploy/healthcheck.py, resource requests on every container, workers that reach the
coordinator through the Service's name, and the image's user and exposed ports from
deploy/Dockerfile. The commands are also parsed by dcrad's own argument parser, so a
renamed flag breaks this test rather than a deployment.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from dcrad.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
K8S = ROOT / "deploy" / "k8s"
COMPOSE = ROOT / "docker-compose.yml"
DOCKERFILE = ROOT / "deploy" / "Dockerfile"
HEALTHCHECK = "/opt/dcrad/healthcheck.py"


def interpolate(value):
    """Compose's ${VAR:-default} / ${VAR-default} / ${VAR}, as with no variable set."""
    if isinstance(value, str):
        return re.sub(r"\$\{([A-Za-z_][A-Za-z0-9_]*)(?::?-([^}]*))?\}", lambda m: m.group(2) or "", value)
    if isinstance(value, dict):
        return {k: interpolate(v) for k, v in value.items()}
    if isinstance(value, list):
        return [interpolate(v) for v in value]
    return value


@pytest.fixture(scope="module")
def compose() -> dict:
    return interpolate(yaml.safe_load(COMPOSE.read_text()))["services"]


@pytest.fixture(scope="module")
def k8s() -> dict:
    """{(kind, name): object} of every manifest in deploy/k8s/."""
    objects = {}
    for path in sorted(K8S.glob("*.yaml")):
        for doc in yaml.safe_load_all(path.read_text()):
            if doc and doc.get("kind") != "Kustomization":
                key = (doc["kind"], doc["metadata"]["name"])
                assert key not in objects, f"{key} defined twice"
                objects[key] = doc
    return objects


def container(k8s, name: str) -> dict:
    deployment = k8s[("Deployment", name)]
    (c,) = [c for c in deployment["spec"]["template"]["spec"]["containers"] if c["name"] == name]
    return c


def compose_env(service: dict) -> dict[str, str]:
    env = service.get("environment") or {}
    if isinstance(env, list):  # the "NAME=value" list form
        env = dict(item.split("=", 1) for item in env)
    return {k: str(v) for k, v in env.items()}


def k8s_env(c: dict) -> dict[str, str]:
    return {e["name"]: str(e["value"]) for e in c.get("env", []) if "value" in e}


def container_ports(service: dict) -> set[int]:
    """Container-side ports a compose service publishes ("127.0.0.1:HOST:CONTAINER")."""
    return {int(str(p).split(":")[-1].split("/")[0]) for p in service.get("ports", [])}


def option(args: list[str], name: str) -> str:
    return args[args.index(name) + 1]


def test_every_manifest_is_listed_in_the_kustomization():
    kustomization = yaml.safe_load((K8S / "kustomization.yaml").read_text())
    assert sorted(kustomization["resources"]) == sorted(
        p.name for p in K8S.glob("*.yaml") if p.name != "kustomization.yaml")


@pytest.mark.parametrize("name", ["coordinator", "worker"])
def test_same_image_command_and_environment(compose, k8s, name):
    service, c = compose[name], container(k8s, name)
    assert c["image"] == service["image"] == compose["coordinator"]["image"]  # one image
    # compose's `command` is the argument list of the image's entrypoint, as k8s' `args`
    assert "command" not in c, "keep the image's entrypoint (it sets the worker's address)"
    assert c["args"] == service["command"]
    assert k8s_env(c) == compose_env(service)
    # nothing the environment does not already say, e.g. from the downward API
    assert [e["name"] for e in c.get("env", [])] == list(k8s_env(c))
    # every variable is one dcrad reads
    source = (ROOT / "dcrad" / "cli.py").read_text() + (ROOT / "coordinator" / "client.py").read_text()
    for var in k8s_env(c):
        assert f'"{var}"' in source, f"{var} is not read by dcrad"


@pytest.mark.parametrize("name, func", [("coordinator", "cmd_coordinator"), ("worker", "cmd_worker")])
def test_commands_parse_with_dcrad(compose, name, func):
    args = build_parser().parse_args(compose[name]["command"])
    assert args.func.__name__ == func
    assert args.host == "0.0.0.0"  # reachable from other containers and pods


def test_same_ports(compose, k8s):
    coordinator, worker = container(k8s, "coordinator"), container(k8s, "worker")
    grpc = int(option(compose["coordinator"]["command"], "--port"))
    web = int(compose_env(compose["coordinator"])["DCRAD_WEB_PORT"])
    k8s_ports = {p["containerPort"] for p in coordinator["ports"]}
    assert k8s_ports == container_ports(compose["coordinator"]) == {grpc, web}
    # workers publish nothing in compose (so they scale); their one port is the --port
    assert not compose["worker"].get("ports")
    assert [p["containerPort"] for p in worker["ports"]] == [int(option(compose["worker"]["command"], "--port"))]
    # the Service exposes exactly the coordinator's ports, under the same numbers
    service = k8s[("Service", "coordinator")]
    named = {p["name"]: p["containerPort"] for p in coordinator["ports"]}
    assert {p["port"] for p in service["spec"]["ports"]} == {grpc, web}
    for p in service["spec"]["ports"]:
        target = p.get("targetPort", p["port"])
        assert named.get(target, target) == p["port"]


def test_workers_reach_the_coordinator_through_the_service(compose, k8s):
    service = k8s[("Service", "coordinator")]
    coordinator = k8s[("Deployment", "coordinator")]
    address = k8s_env(container(k8s, "worker"))["DCRAD_COORDINATOR"]
    host, port = address.rsplit(":", 1)
    assert host == service["metadata"]["name"] == "coordinator"  # compose's service name too
    assert int(port) in {p["port"] for p in service["spec"]["ports"]}
    assert compose_env(compose["worker"])["DCRAD_COORDINATOR"] == address
    assert "coordinator" in compose
    labels = coordinator["spec"]["template"]["metadata"]["labels"]
    assert service["spec"]["selector"].items() <= labels.items()
    assert coordinator["spec"]["selector"]["matchLabels"].items() <= labels.items()


def test_two_workers_by_default_and_scalable(compose, k8s):
    worker = k8s[("Deployment", "worker")]
    assert worker["spec"]["replicas"] == compose["worker"]["scale"] == 2
    assert "container_name" not in compose["worker"]  # a fixed name could not scale
    assert k8s[("Deployment", "coordinator")]["spec"]["replicas"] == 1


@pytest.mark.parametrize("name", ["coordinator", "worker"])
def test_probes_use_the_health_check(compose, k8s, name):
    c = container(k8s, name)
    test = compose[name]["healthcheck"]["test"]
    assert test[0] == "CMD" and test[1] == HEALTHCHECK
    port = option(compose[name]["command"], "--port")
    assert test[1:] == [HEALTHCHECK, f"127.0.0.1:{port}"]
    for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
        assert c[probe]["exec"]["command"] == test[1:], probe


#: Kubernetes quantity suffixes
_UNITS = {"": 1.0, "m": 1e-3, "k": 1e3, "M": 1e6, "G": 1e9, "Ki": 2.0**10, "Mi": 2.0**20, "Gi": 2.0**30, "Ti": 2.0**40}


def quantity(q) -> float:
    """A Kubernetes quantity ("500m", "2Gi", 1) as a number; a malformed one fails the test."""
    m = re.fullmatch(r"([0-9]+(?:\.[0-9]+)?)([A-Za-z]*)", str(q))
    assert m and m.group(2) in _UNITS, f"not a Kubernetes quantity: {q!r}"
    return float(m.group(1)) * _UNITS[m.group(2)]


def test_quantity():
    assert quantity("500m") == 0.5 and quantity(1) == 1 and quantity("2Gi") == 2 * 1024**3
    with pytest.raises(AssertionError):
        quantity("2 GB")


@pytest.mark.parametrize("name", ["coordinator", "worker"])
def test_resource_requests(k8s, name):
    c = container(k8s, name)
    requests, limits = c["resources"]["requests"], c["resources"]["limits"]
    cpu, memory, limit = quantity(requests["cpu"]), quantity(requests["memory"]), quantity(limits["memory"])
    assert cpu > 0 and 0 < memory <= limit
    if name == "coordinator":
        # it holds a whole upload while assembling it (and the scene it meshes): room for two
        env = k8s_env(c)
        upload = int(env.get("DCRAD_MAX_UPLOAD") or build_parser().parse_args(["coordinator"]).max_upload)
        assert limit >= 2 * upload, (limit, upload)
    else:
        assert cpu >= 1  # a worker traces rays: at least one core


def test_results_volume(compose, k8s):
    data = compose_env(compose["coordinator"])["DCRAD_DATA"]
    assert f"results:{data}" in compose["coordinator"]["volumes"]
    deployment = k8s[("Deployment", "coordinator")]
    (mount,) = container(k8s, "coordinator")["volumeMounts"]
    assert mount["mountPath"] == data
    (volume,) = [v for v in deployment["spec"]["template"]["spec"]["volumes"] if v["name"] == mount["name"]]
    assert ("PersistentVolumeClaim", volume["persistentVolumeClaim"]["claimName"]) in k8s


def test_the_image_matches(compose, k8s):
    """The Dockerfile's user, ports, health check and entrypoint are what both files assume."""
    text = DOCKERFILE.read_text()
    uid, gid = re.search(r"^USER (\d+):(\d+)$", text, re.M).groups()
    for name in ("coordinator", "worker"):
        pod = k8s[("Deployment", name)]["spec"]["template"]["spec"]["securityContext"]
        assert pod["runAsNonRoot"] is True
        assert (str(pod["runAsUser"]), str(pod["runAsGroup"])) == (uid, gid)
    exposed = {int(p) for p in re.search(r"^EXPOSE (.+)$", text, re.M).group(1).split()}
    ports = {p["containerPort"] for n in ("coordinator", "worker") for p in container(k8s, n)["ports"]}
    assert ports <= exposed
    assert re.search(r"^HEALTHCHECK .*\n?.*CMD \[\"" + re.escape(HEALTHCHECK), text, re.M)
    assert re.search(r"^COPY deploy/entrypoint\.sh deploy/healthcheck\.py /opt/dcrad/$", text, re.M)
    assert re.search(r'^ENTRYPOINT \["/opt/dcrad/entrypoint\.sh"\]$', text, re.M)
    # the image's default command is the compose coordinator's
    cmd = re.search(r"^CMD (\[.*\])$", text, re.M).group(1)
    assert yaml.safe_load(cmd) == compose["coordinator"]["command"]
    assert compose["coordinator"]["build"]["dockerfile"] == "deploy/Dockerfile"


def test_manifests_follow_the_kubernetes_schema():
    """Strict validation against the Kubernetes OpenAPI schemas, where kubernetes-validate is installed."""
    kv = pytest.importorskip("kubernetes_validate", reason="pip install kubernetes-validate to check the schema")
    for path in sorted(K8S.glob("*.yaml")):
        for doc in yaml.safe_load_all(path.read_text()):
            if doc and doc.get("kind") != "Kustomization":
                kv.validate(doc, kv.latest_version(), strict=True)
