"""The dashboard in a real browser (Debian's chromium, headless, driven by playwright): ``magnet up --devices 5``
with the dashboard on a free loopback port; five rows appear, headings move and match what ``magnet watch heading``
prints for the same message, a device whose hard iron moved after its calibration shows its drift alert and advice
in the fleet table, the header count and the device view within the alert's own delay, and a calibration session
started from the page shows progress and commits.

The moved hard iron: ``dev-004``'s store holds the calibration that exactly undoes its emulated iron (the same
simulator, seed and place as the edge's), but with the hard iron 20 uT away from where the emulator now puts it:
to the compass that is a device whose iron moved after it was calibrated.

Screenshots of each view go to ``$MAGNET_ARTEFACT_DIR/dashboard`` (default: the system's temp folder, under
``magnet-artefacts``): look at them.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from magnet import wire
from magnet.drift import DriftSettings
from magnet.model import Calibration, Quality
from magnet.simulator import SimulatedDevices
from services.calibrator.store import CalibrationStore
from services.common.zenoh_session import free_ports

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[3]
MAGNET = [sys.executable, "-m", "services.cli"]
CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--no-first-run",
]
DRIFT = DriftSettings(window_s=2.0, raise_windows=3, clear_windows=3)
DRIFTED, IRON_MOVE_UT = "dev-004", np.array([14.0, -10.0, 10.0])
LOCATION = (50.45, 30.52)
ARTEFACTS = Path(os.environ.get("MAGNET_ARTEFACT_DIR", Path(tempfile.gettempdir()) / "magnet-artefacts")) / "dashboard"


@pytest.fixture(scope="session")
def chromium() -> Path:
    """Debian's chromium, installed with apt-get when missing (as root); skipped only when that fails."""
    if not CHROMIUM.exists():
        if os.geteuid() != 0 or shutil.which("apt-get") is None:
            pytest.skip("no /usr/bin/chromium and not root with apt-get to install it")
        for command in (
            ["apt-get", "install", "-y", "chromium"],
            ["apt-get", "update"],
            ["apt-get", "install", "-y", "chromium"],
        ):
            done = subprocess.run(
                command,
                capture_output=True,
                text=True,
                timeout=900,
                env={**os.environ, "DEBIAN_FRONTEND": "noninteractive"},
            )
            if done.returncode == 0 and CHROMIUM.exists():
                break
        if not CHROMIUM.exists():
            pytest.skip(f"apt-get install -y chromium failed: {done.stderr.strip()[-300:]}")
    return CHROMIUM


def store_moved_iron(path: Path) -> str:
    """The calibration of DRIFTED's emulated iron with the hard iron moved by IRON_MOVE_UT, stored; its id."""
    sim = SimulatedDevices(5, seed=1, noise_ut=0.3, lat_deg=LOCATION[0], lon_deg=LOCATION[1])  # the edge's defaults
    errors = sim.errors[int(DRIFTED[-3:])]
    calibration = Calibration(
        "ellipsoid",
        errors.hard_iron_ut + IRON_MOVE_UT,
        np.linalg.inv(errors.distortion),
        field_strength=sim.earth.total_ut,
        quality=Quality(residual_rms_ut=0.3, coverage=0.95),
        accepted=True,
    )
    with CalibrationStore(path) as store:
        store.save(wire.DeviceCalibration(DRIFTED, time.time_ns(), calibration))
    return calibration.content_id


@pytest.fixture
def pipeline(tmp_path):
    """``magnet up --devices 5`` with the dashboard on a free port and DRIFTED's moved iron in its store; (page
    address, compass port)."""
    [http_port] = free_ports(1)
    store_moved_iron(tmp_path / "up.db")
    with open(tmp_path / "up.out", "w") as out:  # the child keeps its own descriptor
        proc = subprocess.Popen(
            [
                *MAGNET,
                "up",
                "--devices",
                "5",
                "--speedup",
                "10",
                "--interval",
                "5",
                "--duration",
                "150",
                "--http",
                f"127.0.0.1:{http_port}",
                "--db",
                str(tmp_path / "up.db"),
                "--location",
                ",".join(map(str, LOCATION)),
                "--drift-window",
                f"{DRIFT.window_s:g}",
                "--drift-windows",
                str(DRIFT.raise_windows),
            ],
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=subprocess.STDOUT,
            cwd=REPO,
            env={**os.environ, "CI": "true", "XDG_RUNTIME_DIR": str(tmp_path)},
        )
    try:
        text = _wait_for(lambda: (tmp_path / "up.out").read_text(), r"dashboard at (http://\S+)", proc, 20)
        address = re.search(r"dashboard at (http://\S+)", text).group(1)
        ports = re.search(r"compass 127\.0\.0\.1:(\d+)", text)
        assert address.startswith(f"http://127.0.0.1:{http_port}/?token=")
        _wait_for_listening(http_port, proc, 30)  # up prints the address as it starts the dashboard's process
        yield address, int(ports.group(1))
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _wait_for_listening(port, proc, timeout_s):
    """Until 127.0.0.1:port accepts a connection; fails when ``proc`` ends first or after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            return
        except OSError:
            if proc.poll() is not None:
                pytest.fail("magnet up ended before its dashboard listened")
            time.sleep(0.1)
    pytest.fail(f"the dashboard did not listen on 127.0.0.1:{port} within {timeout_s} s")


def _wait_for(read, pattern, proc, timeout_s):
    """The text ``read()`` returns once ``pattern`` is in it; fails when ``proc`` ends first or after ``timeout_s``."""

    def seen():
        text = read()
        if re.search(pattern, text):
            return text
        if proc.poll() is not None:
            pytest.fail(f"process ended early: {text[-2000:]}")
        return None

    return _until(seen, timeout_s)


#: true in the page once every device in ``first`` ({device: [seq, heading]}) shows a newer message and at least
#: four of their headings moved by more than 0.5 deg
NEWER_AND_MOVED = """first => {
    const cells = [...document.querySelectorAll('#fleet-body td[data-key="true_heading_deg"]')];
    const now = Object.fromEntries(cells.map(td => [td.parentElement.dataset.device, td.dataset]));
    const devices = Object.keys(first);
    const newer = devices.every(d => now[d] && Number(now[d].seq) > first[d][0]);
    const moved = devices.filter(d => now[d] && Math.abs(Number(now[d].heading) - first[d][1]) > 0.5).length;
    return newer && moved >= 4;
}"""
#: resolves after the browser has drawn two more frames
TWO_FRAMES = "() => new Promise(done => requestAnimationFrame(() => requestAnimationFrame(done)))"


def _until(value, timeout_s):
    """``value()`` once it is not None, checked every 0.1 s; fails after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while (result := value()) is None:
        if time.monotonic() > deadline:
            pytest.fail(f"{getattr(value, '__name__', 'condition')} not met within {timeout_s} s")
        time.sleep(0.1)
    return result


def _watch_headings(tmp_path, compass_port):
    """``magnet watch heading`` connected to the compass, printing into a file."""
    with open(tmp_path / "watch.jsonl", "w") as out:  # the child keeps its own descriptor
        return subprocess.Popen(
            [
                *MAGNET,
                "watch",
                "heading",
                "--duration",
                "60",
                "--no-multicast-scouting",
                "--connect",
                f"tcp/127.0.0.1:{compass_port}",
            ],
            stdout=out,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            cwd=REPO,
        )


def _watched(tmp_path) -> dict[tuple[str, int], float]:
    """(device, seq) -> true heading of the message's last sample, from what `magnet watch heading` printed."""
    out = {}
    for line in (tmp_path / "watch.jsonl").read_text().splitlines():
        try:
            message = json.loads(line)
        except ValueError:
            continue
        if "true_heading_deg" in message:
            out[(message["device"], message["seq"])] = message["true_heading_deg"][-1]
    return out


def _watched_once(tmp_path, wanted, count):
    """``_watched`` once it holds at least ``count`` of the (device, seq) ``wanted``, else None."""
    watched = _watched(tmp_path)
    return watched if len(wanted & watched.keys()) >= count else None


def _page_headings(page) -> dict[str, tuple[int, float]]:
    cells = page.eval_on_selector_all(
        '#fleet-body td[data-key="true_heading_deg"]',
        "tds => tds.map(td => [td.parentElement.dataset.device, td.dataset.seq, td.dataset.heading])",
    )
    return {device: (int(seq), float(heading)) for device, seq, heading in cells if seq and heading}


def _shot(page, name):
    ARTEFACTS.mkdir(parents=True, exist_ok=True)
    page.evaluate("window.scrollTo(0, 0)")  # the sticky header at the top of a full-page shot
    page.screenshot(path=str(ARTEFACTS / f"{name}.png"), full_page=True)


def test_dashboard_in_a_browser(chromium, pipeline, tmp_path):
    sync_api = pytest.importorskip("playwright.sync_api", reason="pip package playwright is a test dependency")
    address, compass_port = pipeline
    watch = _watch_headings(tmp_path, compass_port)
    try:
        with sync_api.sync_playwright() as playwright:
            browser = playwright.chromium.launch(executable_path=str(chromium), args=CHROMIUM_ARGS)
            try:
                page = browser.new_page(viewport={"width": 1500, "height": 950})
                errors = []
                page.on("pageerror", lambda exc: errors.append(str(exc)))
                page.set_default_timeout(60_000)  # generous: CI machines are shared; nothing waits when it is fast
                page.goto(address, wait_until="domcontentloaded")
                page.evaluate(SEE_DRIFT, DRIFTED)
                _check_fleet(page, tmp_path)
                _check_drift(page)
                _check_session(page)
                assert errors == [], errors
            finally:
                browser.close()
    finally:
        watch.terminate()
        watch.wait(timeout=10)


def _check_fleet(page, tmp_path):
    page.wait_for_function("document.querySelectorAll('#fleet-body tr').length === 5", timeout=60_000)
    assert "token" not in page.url  # the page keeps the token and takes it out of the address bar
    devices = page.eval_on_selector_all("#fleet-body tr", "trs => trs.map(tr => tr.dataset.device)")
    assert devices == [f"dev-{i:03d}" for i in range(5)]
    page.wait_for_function(
        "document.querySelectorAll('#fleet-body td[data-heading]:not([data-heading=\"\"])').length === 5",
        timeout=20_000,
    )
    first = _page_headings(page)
    page.wait_for_function(NEWER_AND_MOVED, arg={d: [seq, heading] for d, (seq, heading) in first.items()})
    second = _page_headings(page)
    assert all(second[d][0] > first[d][0] for d in first), (first, second)  # newer messages shown
    assert sum(abs(second[d][1] - first[d][1]) > 0.5 for d in first) >= 4, (first, second)  # headings move
    _shot(page, "fleet")
    wanted = {(device, seq) for device, (seq, _) in second.items()}
    watched = _until(lambda: _watched_once(tmp_path, wanted, 4), 20)  # `magnet watch heading` printed them
    matched = 0
    for device, (seq, heading) in second.items():
        if (device, seq) in watched:
            matched += 1
            assert abs((heading - watched[(device, seq)] + 180) % 360 - 180) < 1.0, (device, seq)
    assert matched >= 4, f"the watcher saw {len(watched)} messages but few of the page's: {second}"


#: records in the page when DRIFTED's drift alert first shows in the fleet table: (Date.now(), its data-since), and
#: since when the page looks (``driftWatchFrom``)
SEE_DRIFT = """device => {
    window.driftSeen = null;
    window.driftWatchFrom = Date.now();
    const timer = setInterval(() => {
        const cell = document.querySelector(`#fleet-body tr[data-device="${device}"] .drift`);
        if (cell) { window.driftSeen = [Date.now(), Number(cell.dataset.since)]; clearInterval(timer); }
    }, 50);
}"""


def _check_drift(page):
    """DRIFTED's alert in the fleet table with its advice, in the header count and in the device view."""
    row = f'#fleet-body tr[data-device="{DRIFTED}"]'
    page.wait_for_function("window.driftSeen !== null", timeout=60_000)
    seen_ms, since_ms = page.evaluate("window.driftSeen")
    watching_ms = page.evaluate("window.driftWatchFrom")
    bound_ms = DRIFT.detection_bound_s * 1000
    if watching_ms <= since_ms + bound_ms:  # the page looked before the alert was due: it shows within the bound
        assert 0 < seen_ms - since_ms <= bound_ms + 5000, f"alert shown {seen_ms - since_ms} ms after the departure"
    else:  # the page came late (a busy machine): the alert raised already shows at once
        assert seen_ms - watching_ms <= 5000, f"alert shown {seen_ms - watching_ms} ms after the page looked"
    advice = page.inner_text(f'{row} .drift[data-kind="field_strength"] .advice')
    assert "recalibrate" in advice and "iron" in advice, advice
    assert page.get_attribute(f'{row} td[data-key="state"] .badge', "data-status") == "drifted"
    assert "calibrated \u00b7 drift alert" in page.inner_text(f'{row} td[data-key="state"]')
    page.wait_for_function("Number(document.querySelector('#alert-count').dataset.count) >= 1", timeout=10_000)
    assert re.search(r"\b[1-9]\d* alerts?\b", page.inner_text("#summary")), page.inner_text("#summary")
    for device in ("dev-000", "dev-002", "dev-003"):  # a device whose iron did not move raises nothing
        assert page.query_selector(f'#fleet-body tr[data-device="{device}"] .drift') is None, device
    _shot(page, "fleet-drift")
    page.click(row, no_wait_after=True)
    page.wait_for_selector("#dev-drift:not(.hidden)")
    item = page.inner_text('#dev-drift-list li[data-kind="field_strength"]')
    assert "field strength" in item and "\u00b5T against" in item and advice in item, item
    measured, expected = (float(x) for x in re.findall(r"([\d.]+) \u00b5T", item)[:2])
    assert 3.0 < abs(measured - expected) <= np.linalg.norm(IRON_MOVE_UT) + 1.0, item  # the move shows, no more
    when = page.inner_text('#dev-drift-list li[data-kind="field_strength"] .when')
    assert re.search(r"\d{1,2}:\d{2}", when), when  # a time of day
    assert page.get_attribute("#dev-badges .badge", "data-status") == "drifted"
    page.evaluate(TWO_FRAMES)
    _shot(page, "device-drift")
    page.evaluate("location.hash = '#/'")
    page.wait_for_selector("#fleet-view:not(.hidden)")


def _check_session(page):
    page.click('#fleet-body tr[data-device="dev-001"]', no_wait_after=True)
    page.wait_for_selector("#device-view:not(.hidden)")
    # the dial shows the heading's one sigma: a wedge about the true needle, and "+-" beside the true heading
    page.wait_for_function("document.querySelector('#v-true').textContent.includes('\u00b1')", timeout=20_000)
    assert page.get_attribute("#dial path", "visibility") == "visible"
    assert re.search(r"\u00b1 [\d.]+\u00b0", page.inner_text("#v-true")), page.inner_text("#v-true")
    page.wait_for_function("document.querySelector('#cloud .main-svg') !== null", timeout=30_000)
    page.wait_for_function("document.querySelectorAll('#history-body tr[data-id]').length >= 1", timeout=20_000)
    before = page.get_attribute("#history-body tr:has(.badge.calibrated:text('in force'))", "data-id")
    page.select_option("#c-method-select", "ellipsoid")
    page.click("#b-start")
    page.wait_for_function(
        "document.querySelector('#c-message').textContent.includes('session started')", timeout=10_000
    )
    page.wait_for_function("document.querySelector('#c-state').textContent === 'session'", timeout=10_000)
    assert page.is_disabled("#b-commit"), "Commit waits for the gate"
    page.wait_for_function("parseFloat(document.querySelector('#c-bar').style.width) > 20", timeout=20_000)
    assert page.inner_text("#c-next").strip() != ""  # what to do next is said
    _check_one_coverage_figure(page)
    _shot(page, "device-session")
    page.wait_for_function("document.querySelector('#b-commit').classList.contains('ready')", timeout=45_000)
    assert not page.is_disabled("#b-commit")
    page.click("#b-commit")
    page.wait_for_function("document.querySelector('#c-message').textContent === 'committed'", timeout=10_000)
    page.wait_for_function("document.querySelector('#c-state').textContent === 'calibrated'", timeout=10_000)
    page.wait_for_function("document.querySelectorAll('#history-body tr[data-id]').length >= 2", timeout=10_000)
    page.wait_for_function("document.querySelectorAll('#cloud .scatterlayer .trace .point').length > 100")
    page.wait_for_function(IN_FORCE_FIRST, timeout=10_000)
    committed = page.inner_text("#history-body tr:first-child")
    assert "in force" in committed and re.search(r"session by \S+@\S+", committed), committed  # who committed
    _check_in_force(page)
    _check_one_coverage_figure(page)
    _check_plots(page)
    _shot(page, "device-committed")
    _check_rollback(page, before)
    page.click('.tab[data-cloud="3d"]')
    page.wait_for_function("document.querySelector('#cloud .gl-container') !== null", timeout=30_000)
    page.evaluate(TWO_FRAMES)  # the 3D scene drawn before the screenshot
    _shot(page, "device-3d")


#: the newest calibration in the history table is marked as the one in force
IN_FORCE_FIRST = (
    "(document.querySelector('#history-body tr:first-child') || {textContent: ''}).textContent.includes('in force')"
)


#: the progress bar's coverage and the sphere note's are the same number
SAME_COVERAGE = """() => {
    const bar = /(\\d+) %/.exec(document.querySelector('#c-pct').textContent);
    const note = /Coverage (\\d+) %/.exec(document.querySelector('#sphere-note').textContent);
    return !!(bar && note && bar[1] === note[1]);
}"""


def _check_one_coverage_figure(page):
    """The progress bar and the sphere's note give one figure, the calibrator's coverage, and nothing else."""
    page.wait_for_function(SAME_COVERAGE, timeout=10_000)
    note = page.inner_text("#sphere-note")
    assert "of 100" not in note and len(re.findall(r"\d+ %", note)) == 1, note


def _check_in_force(page):
    """Offset and matrix of the calibration in force, and its export as a JSON file."""
    page.wait_for_function("document.querySelectorAll('#f-matrix td').length === 9", timeout=10_000)
    offset = [float(x) for x in re.findall(r"-?\d+\.\d+", page.inner_text("#f-offset"))]
    assert len(offset) == 3 and "\u00b5T" in page.inner_text("#f-offset"), offset
    with page.expect_download() as download:
        page.click("#b-export")
    record = json.loads(Path(download.value.path()).read_text())
    in_force = page.get_attribute("#history-body tr:first-child", "data-id")
    assert record["id"] == in_force == page.inner_text("#f-id") and record["device"] == "dev-001"
    assert [round(x, 2) for x in record["offset"]] == offset and len(record["matrix"]) == 3


def _check_plots(page):
    """The heading plot draws two lines, true solid and magnetic dashed, over up to 60 s; no legend under a toolbar."""
    page.wait_for_function("document.querySelectorAll('#heading-plot .scatterlayer .trace path.js-line').length >= 2")
    dashes = page.eval_on_selector_all(
        "#heading-plot .scatterlayer .trace",
        "ts => ts.map(t => getComputedStyle(t.querySelector('path.js-line')).strokeDasharray)",
    )
    assert dashes[0] in ("", "none") and dashes[1] not in ("", "none"), dashes
    span = page.evaluate("(() => { const a = document.querySelector('#heading-plot')._fullLayout.xaxis.range;"
                         " return a[1] - a[0]; })()")  # fmt: skip
    assert span == 60, span
    for plot in ("#cloud", "#sphere", "#heading-plot"):
        page.hover(plot)
        boxes = page.evaluate(OVERLAP, plot)
        assert boxes["overlap"] is False, (plot, boxes)


#: the bounding boxes of a plot's legend and toolbar (if shown) and whether they overlap
OVERLAP = """plot => {
    const box = sel => { const e = document.querySelector(`${plot} ${sel}`);
        if (!e) return null; const r = e.getBoundingClientRect();
        return r.width && r.height ? [r.left, r.top, r.right, r.bottom] : null; };
    const legend = box('.legend'), bar = box('.modebar');
    const overlap = !!(legend && bar && legend[0] < bar[2] && bar[0] < legend[2] && legend[1] < bar[3]
        && bar[1] < legend[3]);
    return {legend, bar, overlap};
}"""


def _check_rollback(page, before):
    """Rollback from the history table puts the earlier calibration back in force (the token is in the page)."""
    if before is None:
        return
    page.click(f'#history-body tr[data-id="{before}"] button.rollback')
    page.wait_for_function("document.querySelector('#c-message').textContent.includes('back in force')", timeout=10_000)
    page.wait_for_function(
        f"document.querySelector('#f-id').textContent === '{before}'", timeout=15_000
    )  # the calibration in force is the one rolled back to
    page.wait_for_function(IN_FORCE_FIRST, timeout=10_000)
    first = page.inner_text("#history-body tr:first-child")
    assert "rollback by" in first and "in force" in first, first
