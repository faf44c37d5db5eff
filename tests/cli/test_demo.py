"""``thermofield demo``: the embedded service end to end through its own HTTP API, as ``make demo`` runs it."""

import os
import re
import signal
import socket
import subprocess
import sys
import time

import cv2
import httpx
import numpy as np
import pytest

from services.formats.ply import read_cloud

pytestmark = pytest.mark.integration


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _demo(tmp_path, port, *extra, web_port=None):
    return subprocess.Popen(
        [sys.executable, "-m", "services.cli.main", "demo", "--data-dir", str(tmp_path / "data"),
         "--port", str(port), "--gateway-port", str(_free_port()), "--rerun-port", str(_free_port()),
         "--rerun-web-port", str(web_port or _free_port()), *extra],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)


CHROMIUM = "/usr/bin/chromium"  # Debian's, installed by `make test` (a browser download would need the internet)


def _hot_pixels_in_browser(url: str, timeout_s: float = 420.0) -> int:
    """Open ``url`` in headless Chromium with only 127.0.0.1 reachable, as on a plant network, and wait until
    the page shows a hot part: pixels of the field's colour map (inferno) at its top, yellow to orange, below
    the viewer's top bar. Returns how many there are (0 when none appeared within ``timeout_s``)."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=[
            "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
            "--disable-sync", "--no-first-run"])
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            page.route("**/*", lambda route: route.continue_() if route.request.url.startswith("http://127.0.0.1")
                       else route.abort())
            page.goto(url, timeout=120_000)
            deadline = time.monotonic() + timeout_s
            while time.monotonic() < deadline:
                time.sleep(2)  # a screenshot costs about 0.2 s; the viewer shows the part some seconds after load
                try:
                    shot = page.screenshot(timeout=60_000)
                except Exception:  # the viewer's WebAssembly is still compiling on a loaded machine
                    continue
                bgr = cv2.imdecode(np.frombuffer(shot, np.uint8), cv2.IMREAD_COLOR)[60:]
                blue, green, red = (bgr[..., k].astype(int) for k in range(3))
                hot = int(((red > 200) & (green > 90) & (red - blue > 90)).sum())
                if hot > 500:
                    return hot
            return 0
        finally:
            browser.close()


def _read_until(demo, marker, seconds=600) -> str:
    output = []
    deadline = time.monotonic() + seconds
    for line in demo.stdout:
        output.append(line)
        if marker in line or time.monotonic() > deadline:
            break
    return "".join(output)


def test_demo_scans_inspects_keeps_serving_and_stops_on_ctrl_c_with_130(tmp_path):
    port = _free_port()
    demo = _demo(tmp_path, port)
    try:
        stdout = _read_until(demo, "Ctrl-C stops it")
        assert "keeps running" in stdout, stdout + (demo.stderr.read()[-2000:] if demo.poll() is not None else "")
        secret = re.search(r"API key for this demo.*\n  (\S+)", stdout)[1]
        # the key shown works, as the printed curl command uses it
        scans = httpx.get(f"http://127.0.0.1:{port}/v1/scans", headers={"Authorization": f"Bearer {secret}"},
                          timeout=10)
        assert scans.status_code == 200 and len(scans.json()) == 1
        viewer = re.search(r"in a browser, live: +(http://\S+)", stdout)[1]
        assert "Rerun" in httpx.get(viewer, timeout=10).text  # the web viewer's page, served by the service
        assert _hot_pixels_in_browser(viewer) > 500, "the browser shows no hot part at the printed URL"
        os.killpg(demo.pid, signal.SIGINT)  # Ctrl-C in a terminal reaches the whole process group
        rest, stderr = demo.communicate(timeout=60)
    finally:
        if demo.poll() is None:
            os.killpg(demo.pid, signal.SIGKILL)
    stdout += rest
    assert demo.returncode == 130, stderr[-2000:]
    assert "job succeeded" in stdout and "temperature (deg C): min" in stdout
    verdict = re.search(r"Inspection against part type \w+: (OK|NotOK|NotDecidable)", stdout)
    assert verdict, stdout
    assert "body_diameter: cold" in stdout
    assert "--connect rerun+http://127.0.0.1:" in stdout
    assert "the service has stopped. Start it again with: thermofield serve --data-dir" in stdout
    data = tmp_path / "data"
    field_files = list(data.glob("*-field.ply"))
    assert len(field_files) == 1 and len(list(data.glob("*-field.rrd"))) == 1
    assert len(list(data.glob("*-report.json"))) == 1
    field = read_cloud(field_files[0])
    hot = field["temperature"][np.isfinite(field["temperature"])]
    assert len(field["x"]) > 100_000 and hot.max() > 1000  # the forging is at up to about 1100 degrees C
    assert "Traceback" not in stderr and "\x1b[" not in stderr, stderr  # no tracebacks, no raw terminal codes
    with socket.socket() as probe:  # the service is gone: its port is free again
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        probe.bind(("127.0.0.1", port))


def test_sigint_to_the_demo_alone_stops_the_service_at_once(tmp_path):
    port = _free_port()
    demo = _demo(tmp_path, port, "--exit-after-scan")
    try:
        _read_until(demo, "thermofield: API on")  # the service is starting; interrupt before the scan ends
        demo.send_signal(signal.SIGINT)  # to the demo's process only, not its group
        # The service is stopped by the demo itself; before, it waited 30 s for a signal that never came.
        rest, stderr = demo.communicate(timeout=25)
    finally:
        if demo.poll() is None:
            os.killpg(demo.pid, signal.SIGKILL)
    assert demo.returncode == 130, stderr[-2000:]
    assert "the service has stopped" in rest and "Traceback" not in stderr
    with socket.socket() as probe:  # nothing listens on the service's port any more
        assert probe.connect_ex(("127.0.0.1", port)) != 0


def test_a_port_in_use_is_named_before_anything_starts(tmp_path):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        web_port = busy.getsockname()[1]
        demo = _demo(tmp_path, _free_port(), web_port=web_port)
        _, stderr = demo.communicate(timeout=60)
    assert demo.returncode == 2
    assert f"port {web_port} on 127.0.0.1 (Rerun's web viewer) is in use" in stderr and "--rerun-web-port" in stderr
    assert not (tmp_path / "data").exists()  # nothing was created: no key, no database
