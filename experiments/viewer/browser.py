"""A headless Chromium driven by Playwright, for the live bench and the browser tests.

Playwright cannot download its own browsers here; it drives the Debian ``chromium`` package (installed by
``./run test`` when root) through its executable path.
"""

from __future__ import annotations

import shutil

__all__ = ["CHROMIUM_ARGS", "chromium_path", "browser_unavailable_reason", "launch_chromium"]

CHROMIUM_ARGS = [
    "--no-sandbox",  # root has no user namespace sandbox here
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]


def chromium_path() -> str | None:
    """The Chromium executable, or None."""
    for name in ("chromium", "chromium-browser"):
        found = shutil.which(name)
        if found:
            return found
    return None


def browser_unavailable_reason() -> str | None:
    """Why no browser can be driven here (None when one can)."""
    try:
        import playwright.sync_api  # noqa: F401, PLC0415
    except ImportError:
        return "Playwright is not installed (pip install -e '.[test]')"
    if chromium_path() is None:
        return "no Chromium executable (./run test installs the Debian package 'chromium' when run as root)"
    return None


def launch_chromium(playwright):
    """Launch the system Chromium headless through a started ``sync_playwright()``."""
    return playwright.chromium.launch(executable_path=chromium_path(), args=CHROMIUM_ARGS, headless=True)
