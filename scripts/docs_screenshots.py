"""Look at the built docs site in a real browser: headless Chromium screenshots of the home page,
a guide page and an API page, and a search that must return results.

    make docs
    python scripts/docs_screenshots.py --site site --out scripts/results/docs-screenshots \
        --chromium /usr/bin/chromium

Needs ``playwright`` (``pip install playwright``; only its driver is used, with the system's
Chromium, so no browser is downloaded). Not part of the test suite: the strict build in
``.ci/run`` checks links and references; this checks what a reader sees (navigation, code
highlighting, the search index loading in its web worker, cross-reference links). Prints a table
and writes ``summary.json`` beside the PNGs.
"""

from __future__ import annotations

import argparse
import functools
import http.server
import json
import threading
from pathlib import Path

PAGES = {"home": "/", "guide": "/guide/filtering/", "api": "/api/filters/"}


class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, format: str, *args: object) -> None:
        pass


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--site", default="site", help="the built site (make docs)")
    ap.add_argument("--out", default="scripts/results/docs-screenshots")
    ap.add_argument("--chromium", default="/usr/bin/chromium", help="the Chromium executable")
    ap.add_argument("--query", default="nees", help="a search that must find pages")
    args = ap.parse_args()
    from playwright.sync_api import sync_playwright

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    handler = functools.partial(_Quiet, directory=args.site)
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    base = f"http://127.0.0.1:{server.server_address[1]}"
    rows: dict[str, dict[str, object]] = {}
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=args.chromium, args=["--no-sandbox"])
            page = browser.new_page(viewport={"width": 1280, "height": 900})
            for name, path in PAGES.items():
                page.goto(base + path)
                page.screenshot(path=str(out / f"{name}.png"))
                rows[name] = {
                    "url": path,
                    "nav_links": page.locator("nav.md-nav--primary a").count(),
                    "highlighted_code_blocks": page.locator(".highlight code").count(),
                    "cross_reference_links": page.locator("a.autorefs-internal").count(),
                }
            page.goto(f"{base}/?q={args.query}")
            page.wait_for_selector(".md-search-result__item", timeout=60_000)
            page.screenshot(path=str(out / "search.png"))
            rows["search"] = {
                "url": f"/?q={args.query}",
                "results_shown": page.locator(".md-search-result__item").count(),
                "meta": page.locator(".md-search-result__meta").inner_text(),
            }
            browser.close()
    finally:
        server.shutdown()
    (out / "summary.json").write_text(json.dumps(rows, indent=2) + "\n")
    for name, row in rows.items():
        print(f"{name:8s} " + "  ".join(f"{k}={v}" for k, v in row.items()))


if __name__ == "__main__":
    main()
