"""The Zenoh examples a user copies, run as written: the README's local example and the TLS
and access-control example of docs/zenoh.md, with the daemon and the clients as separate processes on
loopback. Only the port changes (7448 → a free one), so that parallel test runs cannot collide."""

import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from vtolpose.client import PoseClient, ServiceUnreachable
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight

from conftest import free_port

REPO_ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONUNBUFFERED": "1"}


def blocks(text: str, marker: str) -> dict[str, str]:
    """The fenced code blocks after ``<!-- marker`` up to the next marker comment, by language."""
    start = text.index(f"<!-- {marker}")
    end = text.find("<!--", start + 4)
    return dict(re.findall(r"```(\w+)\n(.*?)```", text[start:end if end > 0 else None], re.S))


def command(line: str) -> list[str]:
    args = shlex.split(line)
    assert args[0] == "vtolpose", line
    return [sys.executable, "-m", "vtolpose", *args[1:]]


class Daemon:
    """``vtolpose run ... --hold`` until it says the replay is done; SIGINT on exit, which must end it with 0."""

    def __init__(self, args: list[str], cwd: Path) -> None:
        self.proc = subprocess.Popen(args, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
        line = self.proc.stdout.readline()
        if "replay finished" not in line:
            self.proc.kill()
            raise AssertionError(f"the daemon did not get ready: {line}{self.proc.stderr.read()}")

    def stop(self) -> tuple[int, str, str]:
        self.proc.send_signal(signal.SIGINT)
        out, err = self.proc.communicate(timeout=30)
        return self.proc.returncode, out, err

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


def run_python(code: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True, env=ENV, timeout=60)


def test_the_readme_local_example_works_as_written(tmp_path):
    example = blocks((REPO_ROOT / "README.md").read_text(encoding="utf-8"), "local-zenoh-example")
    simulate, run = [line for line in example["sh"].splitlines() if line.strip()]
    assert "--zenoh" in run and "listen" not in run  # the default endpoint, as a new user would
    subprocess.run(command(simulate), cwd=tmp_path, check=True, capture_output=True, env=ENV, timeout=120)
    port = free_port()
    daemon = Daemon(command(run) + ["--set", f"outputs.zenoh.listen=[tcp/127.0.0.1:{port}]"], tmp_path)
    try:
        client = run_python(example["python"].replace("tcp/127.0.0.1:7448", f"tcp/127.0.0.1:{port}"), tmp_path)
        code, out, err = daemon.stop()
    finally:
        daemon.kill()
    assert client.returncode == 0, client.stderr
    assert re.search(r"^\d+ poses from t = (29|30)\d{9} ns; first position", client.stdout, re.M), client.stdout
    assert "pose at 45 s: [" in client.stdout
    assert code == 0 and "stopped by signal" in out, err
    assert f"listening on tcp/127.0.0.1:{port}" in err  # the daemon says where a client connects


def test_a_client_that_cannot_connect_says_what_to_check():
    port = free_port()  # nothing listens here
    with pytest.raises(ServiceUnreachable, match=rf"connecting to tcp/127.0.0.1:{port}.*Is `vtolpose run \.\.\. --zenoh` running"):
        PoseClient("vtolpose/vtol1", connect=[f"tcp/127.0.0.1:{port}"])


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command to make the certificates")
def test_the_tls_and_access_control_example_of_the_docs(tmp_path):
    docs = (REPO_ROOT / "docs" / "zenoh.md").read_text(encoding="utf-8")
    port = str(free_port())
    subprocess.run(["bash", "-e", "-c", blocks(docs, "example: certificates")["sh"]], cwd=tmp_path, check=True,
                   capture_output=True, timeout=120)
    (tmp_path / "pki" / "acl.json5").write_text(blocks(docs, "example: acl")["json5"])
    (tmp_path / "vehicle-tls.yaml").write_text(blocks(docs, "example: vehicle")["yaml"].replace("7448", port))
    write_flight(simulate_flight("landfill", 60.0, 1), tmp_path / "demo-landfill")
    mapper = blocks(docs, "example: mapper")["python"].replace("7448", port)
    daemon = Daemon(command("vtolpose run --replay demo-landfill --config vehicle-tls.yaml --hold"), tmp_path)
    try:
        allowed = run_python(mapper, tmp_path)
        spare = run_python(mapper.replace("pki/mapper.", "pki/spare."), tmp_path)
        no_certificate = run_python(mapper.replace('certificate="pki/mapper.pem", private_key="pki/mapper.key", ', ""),
                                    tmp_path)
        code, _, err = daemon.stop()
    finally:
        daemon.kill()
    assert allowed.returncode == 0 and "pose at 45 s: [" in allowed.stdout, allowed.stderr
    assert spare.returncode != 0 and "TimeoutError: no vtolpose service under vtolpose/vtol1/" in spare.stderr
    assert no_certificate.returncode != 0 and "ServiceUnreachable" in no_certificate.stderr
    assert code == 0, err
