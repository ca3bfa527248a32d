#!/usr/bin/env python3
"""The scheduler's status page in a real headless browser (.ci/run runs it).

Starts a scheduler with its status address and two worker daemons, submits
the Cornell box, and while it renders loads the page in Chromium (driven by
Selenium through chromium-driver): the page must list both workers, show the
running job with its noise target, and show the preview change as tiles
arrive (its pixels, read back through a canvas, differ between two moments). A screenshot goes
to target/browser/status-page.png. Fails, never skips, without a browser.

    python3 tests/browser/status_page.py [path/to/locus]
"""
import hashlib
import os
import re
import shutil
import socket
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def fail(msg):
    print(f"status page test: FAILED: {msg}", file=sys.stderr)
    sys.exit(1)


try:
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
except ImportError:
    fail("selenium is not installed (pip install selenium)")


def free_port():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def wait(what, cond, timeout=30.0, every=0.1):
    end = time.time() + timeout
    while time.time() < end:
        v = cond()
        if v:
            return v
        time.sleep(every)
    fail(f"timed out waiting for {what}")


def main():
    locus = sys.argv[1] if len(sys.argv) > 1 else os.path.join(ROOT, "target/release/locus")
    chromium = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    driver_bin = shutil.which("chromedriver")
    if not chromium or not driver_bin:
        fail("chromium and chromedriver must be installed (Debian: apt install chromium chromium-driver)")
    out = os.path.join(ROOT, "target/browser")
    os.makedirs(out, exist_ok=True)
    env = dict(os.environ, LOCUS_TOKEN="browser-test", RUST_LOG="warn")
    http = f"127.0.0.1:{free_port()}"
    procs = []
    driver = None
    try:
        sched = subprocess.Popen(
            [locus, "scheduler", "--listen", "127.0.0.1:0", "--http", http],
            env=env, stdout=subprocess.PIPE, text=True)
        procs.append(sched)
        line = sched.stdout.readline()
        m = re.search(r"listening on (\S+)", line)
        if not m:
            fail(f"scheduler did not print its address: {line!r}")
        addr = m.group(1)
        for _ in range(2):
            procs.append(subprocess.Popen(
                [locus, "worker", "--scheduler", addr, "--listen", "127.0.0.1:0", "--threads", "1"],
                env=env, stdout=subprocess.DEVNULL))

        opts = webdriver.ChromeOptions()
        opts.binary_location = chromium
        for a in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                  "--window-size=1400,900"):
            opts.add_argument(a)
        driver = webdriver.Chrome(service=Service(driver_bin), options=opts)
        driver.set_page_load_timeout(30)
        driver.get(f"http://{http}/")
        rows = lambda: driver.execute_script(
            "return document.querySelectorAll('#workers tbody tr').length")
        wait("two workers on the page", lambda: rows() == 2)

        # Long enough to watch (about ten seconds on two cores), and under
        # `forward`, so that the page has traffic between the workers to show.
        client = subprocess.Popen(
            [locus, "submit", "--scheduler", addr, os.path.join(ROOT, "scenes/cornell-box/cornell.toml"),
             "--workers", "2", "--spp", "128", "--fetch", "forward", "-o", os.path.join(out, "job.exr"),
             # A noise target never met: every pass is rendered, one at a
             # time (the barrier between passes), and the page names it.
             "--target-rel-mse", "1e-12"],
            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        procs.append(client)

        # Tile passes in the preview shown.
        tiles = lambda: driver.execute_script(
            "const i = document.getElementById('preview');"
            "return i.dataset.job ? Number(i.dataset.done) : -1;")
        # 16x16 blocks of the preview with no lit pixel (null: no preview).
        dark_blocks = lambda: driver.execute_script(
            "const i = document.getElementById('preview');"
            "if (!i.complete || !i.naturalWidth) return null;"
            "const c = document.createElement('canvas');"
            "c.width = i.naturalWidth; c.height = i.naturalHeight;"
            "const g = c.getContext('2d'); g.drawImage(i, 0, 0);"
            "const d = g.getImageData(0, 0, c.width, c.height).data;"
            "let dark = 0;"
            "for (let by = 0; by < c.height; by += 16) for (let bx = 0; bx < c.width; bx += 16) {"
            "  let lit = false;"
            "  for (let y = by; y < Math.min(by + 16, c.height) && !lit; y++)"
            "    for (let x = bx; x < Math.min(bx + 16, c.width); x++) {"
            "      const k = 4 * (y * c.width + x);"
            "      if (d[k] + d[k + 1] + d[k + 2] > 0) { lit = true; break; }"
            "    }"
            "  if (!lit) dark++;"
            "}"
            "return dark;")
        # The preview's pixels, read back through a canvas.
        pixels = lambda: driver.execute_script(
            "const i = document.getElementById('preview');"
            "if (!i.complete || !i.naturalWidth) return null;"
            "const c = document.createElement('canvas');"
            "c.width = i.naturalWidth; c.height = i.naturalHeight;"
            "const g = c.getContext('2d'); g.drawImage(i, 0, 0);"
            "return Array.from(g.getImageData(0, 0, c.width, c.height).data).join(',');")
        first = wait("a first preview with some tiles", lambda: (t := tiles()) > 0 and t, 60)
        p1 = wait("the first preview's pixels", pixels)
        job_text = driver.find_element("id", "job").text
        if "rendering" not in job_text and "collecting" not in job_text:
            fail(f"the job panel does not show the running job: {job_text!r}")
        if "128 spp to relMSE 1.00e-12" not in job_text:
            fail(f"the job panel does not show the job's noise target: {job_text!r}")
        second = wait("more tiles in the preview", lambda: (t := tiles()) > first and t, 60)
        p2 = wait("the second preview's pixels", pixels)
        if hashlib.sha256(p1.encode()).digest() == hashlib.sha256(p2.encode()).digest():
            fail(f"the preview did not change between {first} and {second} tiles")
        total = driver.execute_script(
            "return Number(document.querySelector('#job').textContent.match(/\\/ (\\d+) tile passes/)[1])")
        # Progressive passes: once the first pass is in (every tile at one
        # sample), the preview covers the whole image, not some tiles.
        passes = driver.execute_script(
            "return Number(document.querySelector('#job').textContent.match(/pass \\d+ of (\\d+)/)[1])")
        wait("the first pass in the preview", lambda: tiles() >= total // passes, 60)
        dark = wait("the preview's blocks", lambda: (d := dark_blocks()) is not None and (d,), 30)[0]
        if dark:
            fail(f"{dark} blocks of 16x16 pixels of the preview are black after the first pass")
        wait("a quarter of the tile passes", lambda: tiles() >= total // 4, 60)
        driver.save_screenshot(os.path.join(out, "status-page.png"))
        worker_text = driver.find_element("id", "workers").text
        if worker_text.count("busy") != 2:
            fail(f"both workers should show busy: {worker_text!r}")
        if client.wait(timeout=120) != 0:
            fail("the submitted job failed")
        wait("the ended job on the page", lambda: "done" in driver.find_element("id", "ended").text)
        ended = driver.find_element("id", "ended").text
        if not re.search(r"\d\.\d\de-\d", ended):
            fail(f"the ended job shows no estimated relMSE: {ended!r}")
        if "128 spp to relMSE 1.00e-12" not in ended:
            fail(f"the ended job does not show its samples and noise target: {ended!r}")
        traffic = wait("the traffic between the workers",
                       lambda: driver.find_element("id", "traffic").text)
        if not re.search(r"\d+(\.\d)? (KiB|MiB|GiB)", traffic):
            fail(f"no traffic shown between the workers of a `forward` job: {traffic!r}")
        driver.save_screenshot(os.path.join(out, "status-page-done.png"))
        print(f"status page test: ok: 2 workers listed, preview changed from {first} to {second} tile passes, "
              f"whole image after the first of {passes} passes; "
              f"screenshots in {out}")
    finally:
        if driver is not None:
            driver.quit()
        for p in reversed(procs):
            if p.poll() is None:
                p.terminate()
        for p in procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()


if __name__ == "__main__":
    main()
