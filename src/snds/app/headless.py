"""Headless Chromium for the page's browser test and its benchmark: Debian's ``chromium``
(``apt-get install chromium``) driven by Playwright, reaching nothing but the page's server.

Playwright's own browser downloads are not used (``playwright install`` is never needed).
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

__all__ = ["ARGS", "CHROMIUM", "available", "launch"]

#: The Chromium executable.
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
#: Flags for a headless Chromium that makes no connection of its own.
ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


def available() -> bool:
    """Whether Chromium is installed."""
    return Path(CHROMIUM).is_file()


def launch(playwright: Any) -> Any:
    """A headless Chromium browser of a started ``sync_playwright()``."""
    return playwright.chromium.launch(executable_path=CHROMIUM, args=ARGS)
