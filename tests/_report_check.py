"""Do HTML pages and their images load? Checked in headless Chromium.

:func:`images_in_chromium` checks one report page opened from its file.
:func:`pages_in_chromium` checks a whole site (the documentation) in one Chromium run: the
site is served over HTTP on the loopback interface, and one checking page loads every page
in turn in an iframe (a few at a time), then every image on it.
"""

from __future__ import annotations

import functools
import json
import re
import shutil
import subprocess
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest

CHECK_SCRIPT = """<script>
window.addEventListener("load", () => {
  const images = [...document.images];
  const broken = images.filter(i => !(i.complete && i.naturalWidth > 0))
                       .map(i => i.getAttribute("src"));
  const out = document.createElement("pre");
  out.id = "image-check";
  out.textContent = JSON.stringify({total: images.length, broken: broken});
  document.body.appendChild(out);
});
</script>"""

#: The checking page of :func:`pages_in_chromium`; PAGES and PARALLEL are filled in.
SITE_CHECK_PAGE = """<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>site check</title></head><body><script>
const pages = PAGES;
const results = {};

function probe(image) {  // does the image's URL give a picture? (lazy images included)
  const source = image.getAttribute("src");
  const url = image.currentSrc || image.src;
  return new Promise(resolve => {
    const copy = new Image();
    copy.onload = () => resolve(copy.naturalWidth > 0 || /\\.svg$/i.test(url) ? null : source);
    copy.onerror = () => resolve(source);
    copy.src = url;
  });
}

async function check(path) {
  const result = {status: 0, loaded: false, images: 0, broken: [], error: null};
  try {
    const response = await fetch(path, {cache: "no-store"});
    result.status = response.status;
    if (response.ok) {
      const frame = document.createElement("iframe");
      frame.style.width = "1200px";
      frame.style.height = "900px";
      const loaded = new Promise(resolve => frame.addEventListener("load", resolve));
      frame.src = path;
      document.body.appendChild(frame);
      await loaded;
      const page = frame.contentDocument;
      result.loaded = page.readyState === "complete" && page.body !== null
                      && page.body.textContent.trim().length > 0;
      const images = [...page.images];
      result.images = images.length;
      result.broken = (await Promise.all(images.map(probe))).filter(s => s !== null);
      frame.remove();
    }
  } catch (error) {
    result.error = String(error);
  }
  results[path] = result;
}

async function main() {
  const queue = pages.slice();
  const worker = async () => { while (queue.length) { await check(queue.shift()); } };
  await Promise.all(Array.from({length: PARALLEL}, worker));
  const out = document.createElement("pre");
  out.id = "site-check";
  out.textContent = JSON.stringify(results);
  document.body.appendChild(out);
}
main();
</script></body></html>"""


def chromium() -> str:
    """The Chromium executable; skips the test where it is not installed."""
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        pytest.skip("Debian's chromium is not installed (make test installs it)")
    return browser


def _dump_dom(url: str, *, budget_ms: int, timeout_s: float) -> subprocess.CompletedProcess:
    """Load `url` in headless Chromium and return its DOM once `budget_ms` of virtual time
    (time in which the page waits for nothing) has passed."""
    return subprocess.run(
        [chromium(), "--headless", "--no-sandbox", "--disable-gpu",
         f"--virtual-time-budget={budget_ms}", "--dump-dom", url],
        capture_output=True, text=True, timeout=timeout_s, check=False,
    )  # fmt: skip


def images_in_chromium(page: Path) -> dict:
    """Load `page` (a copy with a checking script) in headless Chromium: images loaded."""
    chromium()
    probe = page.with_name("_image_check.html")
    probe.write_text(page.read_text().replace("</body>", CHECK_SCRIPT + "</body>"))
    result = _dump_dom(probe.as_uri(), budget_ms=10000, timeout_s=120)
    probe.unlink()
    found = re.search(r'<pre id="image-check">(.*?)</pre>', result.stdout)
    assert found, f"chromium gave no result (status {result.returncode}): {result.stderr[-500:]}"
    return json.loads(found.group(1).replace("&quot;", '"'))


@contextmanager
def _serve(root: Path, extra: dict[str, str]) -> Iterator[str]:
    """Serve the files under `root`, and the pages `extra` (path → HTML), on a loopback
    port; yields the server's URL."""

    class Handler(SimpleHTTPRequestHandler):
        def do_GET(self) -> None:
            text = extra.get(self.path)
            if text is None:
                super().do_GET()
                return
            body = text.encode()
            self.send_response(200)
            self.send_header("Content-Type", "text/html; charset=utf-8")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, format: str, *args: object) -> None:
            """Requests are not logged (the test reads the browser's results instead)."""

    server = ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Handler, directory=root))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()
        thread.join()


def pages_in_chromium(
    root: Path, pages: Sequence[str], *, parallel: int = 6, timeout_s: float = 240
) -> dict[str, dict]:
    """Load each of `pages` (paths relative to `root`) and every image on it in headless
    Chromium, in one browser run.

    Returns
    -------
    dict
        Page → ``status`` (HTTP), ``loaded`` (the page finished loading and has text),
        ``images`` (how many), ``broken`` (the ``src`` of each image that did not load)
        and ``error`` (a script error of the check, or None).
    """
    chromium()
    page = SITE_CHECK_PAGE.replace("PAGES", json.dumps(["/" + p for p in pages]))
    page = page.replace("PARALLEL", str(parallel))
    with _serve(root, {"/__site_check__.html": page}) as url:
        result = _dump_dom(f"{url}/__site_check__.html", budget_ms=600_000, timeout_s=timeout_s)
    found = re.search(r'<pre id="site-check">(.*?)</pre>', result.stdout, re.S)
    assert found, f"chromium gave no result (status {result.returncode}): {result.stderr[-500:]}"
    text = found.group(1).replace("&quot;", '"').replace("&lt;", "<").replace("&gt;", ">")
    checked = json.loads(text.replace("&amp;", "&"))
    return {path.removeprefix("/"): value for path, value in checked.items()}
