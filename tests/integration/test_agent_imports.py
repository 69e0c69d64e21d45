"""What the node agent's process loads: no kopf, no pymavlink, no kubernetes package, no
pydantic, no prometheus_client unless metrics are on, no libcrypto in a standalone run.

Each check starts a fresh interpreter (``python -c``) and reads its ``sys.modules``, since
this test process has imported all of those already.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

from tests.support.specdoc import SPEC


def test_agent_without_metrics_does_not_import_prometheus_client() -> None:
    code = "import sys, roost_agent.main; print('prometheus_client' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_standalone_agent_imports_neither_kopf_nor_heavy_clients() -> None:
    """The agent must not import kopf; standalone it also skips the Kubernetes client and
    numpy (pulled in by pymavlink's mavutil), which would cost tens of MB on a vehicle."""
    probe = (
        "import sys, roost_agent.main, roost_agent.agent; "
        "print(sorted(m for m in ('kopf', 'kubernetes', 'numpy') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_the_agent_never_imports_pymavlink() -> None:
    """Its MAVLink is roost_mavlink.codec: pymavlink's generated dialect alone costs ~7 MB
    of memory on a companion computer."""
    probe = (
        "import sys, roost_agent.main, roost_agent.agent, roost_agent.hub; "
        "print(sorted(m for m in sys.modules if m.split('.')[0] == 'pymavlink'))"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_the_agent_in_cluster_mode_never_imports_the_kubernetes_package_nor_pydantic() -> None:
    """Its API client goes through roost_kube's minimal transport (about 13 MB less), and
    it reads and writes its RedundantAutopilot through roost_api.plain (about 15 MB less)."""
    probe = (
        "import sys, pathlib, roost_agent.main, roost_agent.publisher; "
        "from roost_agent.kube import AgentKube; "
        "AgentKube.from_environment(pathlib.Path(sys.argv[1])); "
        "print('kubernetes' in sys.modules, 'pydantic' in sys.modules)"
    )
    with tempfile.TemporaryDirectory() as tmp:
        config = Path(tmp) / "kubeconfig"
        config.write_text(
            "current-context: x\n"
            "contexts: [{name: x, context: {cluster: x, user: x}}]\n"
            "clusters: [{name: x, cluster: {server: 'https://127.0.0.1:1'}}]\n"
            "users: [{name: x, user: {token: t}}]\n"
        )
        out = subprocess.run(
            [sys.executable, "-c", probe, str(config)], capture_output=True, text=True, check=True
        )
    assert out.stdout.strip() == "False False"


def _probe(code: str, *args: str) -> str:
    out = subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, check=True
    )
    return out.stdout.strip()


def test_the_standalone_agent_never_imports_pydantic() -> None:
    """pydantic costs a companion computer ~15 MB with the models, plus libcrypto
    (hashlib, via secrets) which the agent maps only with MAVLink signing on."""
    probe = (
        "import sys, roost_agent.main, roost_agent.agent, roost_agent.hub, roost_agent.state; "
        "print(sorted(m for m in ('pydantic', 'pydantic_core', 'hashlib', 'decimal') "
        "if m in sys.modules))"
    )
    assert _probe(probe) == "[]"


def test_a_standalone_agent_run_loads_neither_pydantic_nor_libcrypto(tmp_path: Path) -> None:
    """A real run: spec from a config file, two autopilot links, a saved state, status out."""
    config = tmp_path / "spec.json"
    spec = json.loads(json.dumps(SPEC))
    del spec["command"], spec["hub"]
    config.write_text(json.dumps(spec))
    probe = (
        "import sys, threading, roost_agent.main as m; "
        "threading.Timer(1.5, lambda: __import__('os').kill(__import__('os').getpid(), 15))"
        ".start(); "
        "code = m.main(['--config', sys.argv[1], '--state-dir', sys.argv[2], "
        "'--status-interval', '0.2']); "
        "maps = open('/proc/self/maps').read(); "
        "print('pydantic' in sys.modules, 'pydantic_core' in maps, 'libcrypto' in maps, "
        "file=sys.stderr)"
    )
    out = subprocess.run(
        [sys.executable, "-c", probe, str(config), str(tmp_path / "state")],
        capture_output=True,
        text=True,
        check=False,
        timeout=60,
    )
    assert out.stderr.strip().splitlines()[-1] == "False False False", out.stderr
    assert (tmp_path / "state" / "agent-state.json").exists()
    assert '"status"' in out.stdout
