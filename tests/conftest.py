"""Shared fixtures: emulators served over real ptys, TCP and RFC 2217, and ser2net; and
``@pytest.mark.virtual``, which runs an async test on virtual time.

Virtual time (docs/clock.md): an async test marked ``@pytest.mark.virtual`` runs, with its
async fixtures, on :class:`cellctl.clock.VirtualLoop`, whose time jumps to the next timer
whenever every task waits. The code under test is unchanged (``asyncio.sleep``, timeouts and
the Clock follow the loop); a wait of a minute costs what its work costs. The marker's
keywords go to the loop: ``@pytest.mark.virtual(allow_real_io=True)`` takes real sockets and
waits in real time while one is open. A test on virtual time joins machines through
``mem://`` (``CellRig`` does so by itself on a virtual loop).

What stays on real time, on purpose (these prove the byte paths and real-time behaviour):
the drivers against the emulators over ptys, TCP and RFC 2217 (``robot_served``, ser2net,
test_link, test_robot_*, test_mill_*), the PLC over Modbus/TCP (test_plc), one batch of the
cell over ptys and RFC 2217 (test_cell_e2e), everything through a subprocess (``cellctl
run``, ``emulate``, ``factory``, ``service``), the broker (Mosquitto), the console in tmux and
the dashboard in Chromium.
"""

from __future__ import annotations

import asyncio
import atexit
import inspect
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import AsyncIterator, Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio
from hypothesis import settings
from playwright.async_api import Browser, async_playwright
from playwright.async_api import Error as PlaywrightError

from cellctl.clock import RealClock, VirtualLoop
from cellctl.emulators.serve import Server, serve
from cellctl.kinds.ibm7545.emulator import Ibm7545Emulator
from cellctl.link import ROBOT_LINE
from cellctl.link.lock import RUNTIME_ENV

TRANSPORTS = ["pty", "socket", "rfc2217"]

# Six workers on two cores can hold any example past Hypothesis's 200 ms deadline (one took
# 574 ms for 0.02 ms of work): a correct test would fail for the box's load. A test that
# bounds a time says so in its own settings.
settings.register_profile("cellctl", deadline=None)
settings.load_profile("cellctl")


def pytest_configure(config: pytest.Config) -> None:
    cache_bytecode()
    own_runtime_dir()
    config.addinivalue_line(
        "markers",
        "virtual(**loop_options): run this async test and its async fixtures on cellctl's "
        "VirtualLoop (time jumps when every task waits); keywords go to VirtualLoop",
    )
    config.addinivalue_line(
        "markers",
        "alone: a real-time run measured against the machines' own times; `make test` runs "
        "these after the others, one at a time, so no other test loads the box meanwhile",
    )


def own_runtime_dir() -> None:
    """Give this test process (each xdist worker) its own lock and socket directory, which
    the processes its tests start inherit. Link locks are per user: two workers' example cells
    name one PLC (modbus://192.0.2.20:502), and a console in one worker's test would hold it
    against ``cellctl run`` in another's. Within a worker tests run one after another, so a
    lock a test leaves behind still shows."""
    directory = tempfile.mkdtemp(prefix="cellctl-run-")
    os.environ[RUNTIME_ENV] = directory
    atexit.register(shutil.rmtree, directory, True)


def cache_bytecode() -> None:
    """Use and keep compiled bytecode when the environment turned caching off
    (PYTHONDONTWRITEBYTECODE). Some 300 Pythons the tests start (every ``cellctl`` command,
    ``cellctl run``, the factory, the workers) import cellctl: without a cache each compiled
    every module from source again, about a quarter of its start-up. It is kept in the usual
    ``__pycache__`` beside each module (git ignores them), where pip compiled the installed
    packages; the processes the tests start inherit the setting."""
    if not sys.dont_write_bytecode:
        return  # caching is on already
    os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
    sys.dont_write_bytecode = False


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if item.get_closest_marker("virtual") is None:
            continue
        func = getattr(item, "obj", None)
        if not inspect.iscoroutinefunction(func):
            raise pytest.UsageError(f"{item.nodeid}: mark.virtual is for async tests only")


#: The signals a test's processes are stopped with.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def _signal_state() -> tuple[object, ...]:
    handlers = [signal.getsignal(sig) for sig in STOP_SIGNALS]
    blocked = signal.pthread_sigmask(signal.SIG_BLOCK, [])
    return (*handlers, sorted(sig for sig in blocked if sig in STOP_SIGNALS))


@pytest.fixture(autouse=True)
def own_state_home(
    tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each test's own ``$XDG_STATE_HOME`` (for it and the commands it starts): a machine
    driven by ``--link`` outside a cell keeps its host state there by its link's name, and
    a port another test's emulator had is given again (its "initialized" is not this one's)."""
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path_factory.mktemp("state-home")))


@pytest.fixture(autouse=True)
def signals_left_as_found() -> Iterator[None]:
    """Fail the test that leaves Ctrl-C or SIGTERM handled otherwise in this process (a
    command run in process, a loop's signal handler): an ignored or blocked signal passes to
    every process a later test starts (exec keeps both), which then cannot be stopped."""
    handlers = {sig: signal.getsignal(sig) for sig in STOP_SIGNALS}
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, [])
    before = _signal_state()
    yield
    after = _signal_state()
    if after != before:
        # Put back what was found, so that only this test fails, not the ones after it.
        for sig, handler in handlers.items():
            if handler is not None:
                signal.signal(sig, handler)
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        pytest.fail(f"the test left SIGINT/SIGTERM handling changed: {before} -> {after}")


def _real_loop() -> asyncio.AbstractEventLoop:
    return asyncio.new_event_loop()


def pytest_asyncio_loop_factories(
    config: pytest.Config, item: pytest.Item
) -> dict[str, Callable[[], asyncio.AbstractEventLoop]]:
    """The event loop an async test runs on: a VirtualLoop for ``@pytest.mark.virtual``."""
    marker = item.get_closest_marker("virtual")
    if marker is None:
        return {"real": _real_loop}
    if marker.args:
        raise pytest.UsageError(f"{item.nodeid}: mark.virtual takes keywords only")
    options = dict(marker.kwargs)
    return {"virtual": lambda: VirtualLoop(**options)}


CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-dev-shm-usage",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


# One Chromium per test process: starting one (and Playwright's driver) costs more CPU than
# most page tests, and every test opens its own context (cookies, storage and page of its
# own). Its tests run on the session's event loop, where the browser lives.
IN_BROWSER = pytest.mark.asyncio(loop_scope="session")


@pytest_asyncio.fixture(scope="session", loop_scope="session")
async def browser() -> AsyncIterator[Browser]:
    if shutil.which(CHROMIUM) is None:
        pytest.fail(
            f"Chromium is not installed at {CHROMIUM}: `make test` installs Debian's chromium "
            "(as root), or run `apt-get install chromium`"
        )
    async with async_playwright() as p:
        try:
            found = await p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        except PlaywrightError as e:
            pytest.fail(f"Chromium ({CHROMIUM}) did not start: {e}")
        try:
            yield found
        finally:
            await found.close()


#: How long a page in Chromium is given to show a change (ms): a deadline for a loaded box,
#: not a timing figure (how fast a change is pushed is bench/api_push.py's).
SEEN_MS = 20_000


def listen_url(transport: str) -> str:
    """Where to serve an emulator for ``transport``: a new pty or a free loopback port."""
    return "pty" if transport == "pty" else f"{transport}://127.0.0.1:0"


def free_port() -> int:
    """A loopback port free now, for a server this test starts at once. Another process may
    take it later: a port where nothing must answer is :func:`refusing_port`'s."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def refusing_port() -> socket.socket:
    """A socket holding a loopback port where a connection is refused: it is bound and never
    listens, so no other test's server can take the port while it is open (a port from
    :func:`free_port` could be anyone's by the time it is dialled). Use it as a context
    manager; its number is ``held.getsockname()[1]``; close it to serve there after all."""
    held = socket.socket()
    held.bind(("127.0.0.1", 0))
    return held


@dataclass
class Served:
    emulator: Ibm7545Emulator
    server: Server

    @property
    def url(self) -> str:
        return self.server.url


@pytest.fixture(params=TRANSPORTS)
async def robot_served(request: pytest.FixtureRequest) -> AsyncIterator[Served]:
    """A fast robot emulator (no pacing, time x200) over each transport in turn."""
    emulator = Ibm7545Emulator(time_scale=200.0)
    server = await serve(emulator, listen_url(request.param), ROBOT_LINE, pacing=False)
    yield Served(emulator, server)
    await server.close()


class Ser2net:
    """A real ser2net in RFC 2217 mode in front of a serial device (here: a pty)."""

    def __init__(self, device: str, line: str, tmp: Path) -> None:
        self.port = free_port()
        conf = tmp / "ser2net.yaml"
        conf.write_text(
            "connection: &con1\n"
            f"  accepter: telnet(rfc2217),tcp,127.0.0.1,{self.port}\n"
            f"  connector: serialdev,{device},{line},local\n"
            "  options:\n"
            "    kickolduser: true\n"
        )
        self.proc = subprocess.Popen(
            ["ser2net", "-n", "-d", "-c", str(conf), "-P", str(tmp / "ser2net.pid")],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        self.url = f"rfc2217://127.0.0.1:{self.port}"

    async def wait_listening(self, timeout: float = 10.0) -> None:
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while True:
            try:
                _, w = await asyncio.open_connection("127.0.0.1", self.port)
                w.close()
                return
            except OSError:
                if loop.time() > deadline or self.proc.poll() is not None:
                    raise RuntimeError("ser2net did not start listening") from None
                await asyncio.sleep(0.05)

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(5)
        except subprocess.TimeoutExpired:
            self.proc.kill()


@pytest.fixture
def ser2net_available() -> Iterator[None]:
    if shutil.which("ser2net") is None:
        pytest.skip("ser2net is not installed (make test installs it)")
    yield


#: Limits of a check of a hostile input (:func:`run_limited`): address space, CPU seconds (the
#: heaviest case takes about 10), and wall seconds against a child that neither ends nor
#: computes. The limit is on CPU, not the clock's: a box busy with other tests stretches a
#: check's wall time (a 10 s one took over 60 s beside five other workers), not its work.
LIMITED_MEMORY = 1 << 30
LIMITED_CPU_S = 40
LIMITED_WALL_S = 280.0


def released_together(
    script: str, argvs: list[list[str]], timeout: float
) -> list[tuple[int, str, str]]:
    """Python ``script`` once per argument list in ``argvs``, in processes of their own: each
    prints ``ready`` and waits for ``go`` on its stdin, sent to all once all are ready, so
    they race. Each one's (return code, stdout, stderr), within ``timeout`` s of the go."""
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", script, *argv],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for argv in argvs
    ]
    for p in procs:
        assert p.stdout is not None and p.stdout.readline().strip() == "ready"
    for p in procs:
        assert p.stdin is not None
        p.stdin.write("go\n")
        p.stdin.flush()
    done = []
    for p in procs:
        out, err = p.communicate(timeout=timeout)
        done.append((p.returncode, out, err))
    return done


def run_limited(script: str, *args: str) -> str:
    """Run Python ``script`` (``sys.argv[1:]`` = ``args``) in a child whose address space and
    CPU time are limited: its output. A child that grows or computes without bound fails the
    test (its limit named) instead of the machine."""
    prologue = (
        "import resource\n"
        f"resource.setrlimit(resource.RLIMIT_AS, ({LIMITED_MEMORY}, {LIMITED_MEMORY}))\n"
        # SIGXCPU at the soft limit (the hard one, a little later, would be a bare SIGKILL).
        f"resource.setrlimit(resource.RLIMIT_CPU, ({LIMITED_CPU_S}, {LIMITED_CPU_S + 5}))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", prologue + script, *args],
        capture_output=True,
        text=True,
        timeout=LIMITED_WALL_S,
        check=False,
    )
    over = done.returncode in (-signal.SIGXCPU, -signal.SIGKILL)
    assert not over, f"the check took over {LIMITED_CPU_S} s of CPU (or was killed)"
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout


CELLCTL = [str(Path(sys.executable).parent / "cellctl")]


@contextmanager
def emulator_process(*args: str) -> Iterator[str]:
    """``cellctl emulate ARGS`` in its own process; yields the URL it says to drive it with
    (``--link URL``, or a dnc.toml's ``link = "URL"``)."""
    proc = subprocess.Popen([*CELLCTL, "emulate", *args], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        url = ""
        for row in proc.stdout:
            found = re.search(r'(?:--link |link = ")([^"\s]+)', row)
            if found:
                url = found.group(1)
                break
        assert url, "the emulator did not say where it listens"
        yield url
    finally:
        proc.terminate()
        proc.wait(timeout=10)


@contextmanager
def emulated_cell_process(cell: Path, time_scale: str, poll_period: float = 0.1) -> Iterator[Path]:
    """``cellctl emulate cell`` writing ``cell`` in its own process, its poll period set for
    tests; yields ``cell`` once every machine listens."""
    proc = subprocess.Popen(
        [*CELLCTL, "--cell", str(cell), "emulate", "cell", "--time-scale", time_scale],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        for line in proc.stdout:
            if line.strip().startswith("plc"):
                break
        toml = cell / "cell.toml"
        text = toml.read_text()
        toml.write_text(re.sub(r"poll_period = [0-9.]+", f"poll_period = {poll_period}", text))
        yield cell
    finally:
        proc.terminate()
        proc.wait(10)


# -- a certificate authority for the broker's TLS listener --------------------------------------


@dataclass(frozen=True)
class CaFiles:
    """A CA made for one test, and a broker certificate it signed for 127.0.0.1/localhost."""

    ca: Path  # the CA's certificate (PEM): what a client trusts
    certfile: Path  # the broker's certificate (PEM)
    keyfile: Path  # the broker's key (PEM, 0600)


def make_ca(directory: Path, name: str = "cellctl test CA") -> CaFiles:
    """A fresh CA in ``directory`` and a broker certificate signed by it (``cryptography``)."""
    import datetime
    import ipaddress

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    directory.mkdir(parents=True, exist_ok=True)
    now = datetime.datetime.now(datetime.UTC)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])
    ca_cert = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True, content_commitment=False, key_encipherment=False,
                data_encipherment=False, key_agreement=False, key_cert_sign=True,
                crl_sign=True, encipher_only=False, decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(
            x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False
        )
        .sign(ca_key, hashes.SHA256())
    )  # fmt: skip
    key = ec.generate_private_key(ec.SECP256R1())
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "localhost")]))
        .issuer_name(ca_name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(
            x509.SubjectAlternativeName(
                [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
            ),
            critical=False,
        )
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()),
            critical=False,
        )
        .sign(ca_key, hashes.SHA256())
    )
    pem = serialization.Encoding.PEM
    out = CaFiles(directory / "ca.crt", directory / "broker.crt", directory / "broker.key")
    out.ca.write_bytes(ca_cert.public_bytes(pem))
    out.certfile.write_bytes(cert.public_bytes(pem))
    out.keyfile.touch(mode=0o600)
    out.keyfile.write_bytes(
        key.private_bytes(pem, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())
    )
    return out


class SetClock(RealClock):
    """A clock whose wall time the test sets (``clock.at = ...``), so a journal's figures are
    exact and need no waiting; its monotonic time stays real."""

    def __init__(self, at: float = 1000.0) -> None:
        super().__init__()
        self.at = at

    def now(self) -> float:
        return self.at


def wait_until(condition: Callable[[], object], what: str, timeout: float = 60.0) -> None:
    """Poll ``condition()`` until true; fail naming ``what`` after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


async def until(condition: Callable[[], object], what: str, timeout: float = 60.0) -> Any:
    """The same from inside the event loop: other tasks run while it waits. ``condition`` may
    be a coroutine function (a call to make each time); the true value it gave is returned."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while True:
        value = condition()
        if inspect.isawaitable(value):
            value = await value
        if value:
            return value
        if loop.time() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.02)
