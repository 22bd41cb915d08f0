"""``cellctl dashboard`` opens the browser with a code good once, not the token: a browser
keeps its URL in its command line, which every user of the host reads (``ps``). The page
swaps the code for the token; a code spent, or made up, opens nothing."""

from __future__ import annotations

import asyncio
import os
import stat
import subprocess
from pathlib import Path

from tests.conftest import CELLCTL, IN_BROWSER, SEEN_MS
from tests.test_dashboard import Dash, dash  # noqa: F401 (the fixture)

# On the session's event loop, where the browser lives (tests/conftest.py).
pytestmark = IN_BROWSER


async def test_the_browser_is_given_a_code_not_the_token(
    dash: Dash,  # noqa: F811
    tmp_path: Path,
) -> None:
    directory = dash.rig.directory
    port = int(dash.base.rsplit(":", 1)[1])
    toml = directory / "cell.toml"
    toml.write_text(toml.read_text() + f'\n[api]\nlisten = "127.0.0.1:{port}"\n')
    argv = tmp_path / "argv.txt"
    browser = tmp_path / "browser.sh"  # a browser that notes its command line
    browser.write_text(f'#!/bin/sh\nprintf "%s\\n" "$@" > {argv}\n')
    browser.chmod(browser.stat().st_mode | stat.S_IXUSR)
    env = {**os.environ, "BROWSER": str(browser)}
    opened = await asyncio.to_thread(
        subprocess.run,
        [*CELLCTL, "--cell", str(directory), "dashboard"],
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
    )
    assert opened.returncode == 0, opened.stdout + opened.stderr
    assert dash.token not in opened.stdout + opened.stderr
    given = argv.read_text().strip()
    assert dash.token not in given, given
    assert given.startswith(f"{dash.base}/#code="), given
    # The page swaps the code for the token and shows the live cell, the code out of sight.
    page = dash.page
    await page.goto(given)
    await page.locator("#connection.good").wait_for(timeout=SEEN_MS)
    assert "code=" not in page.url
    # Spent: the same URL again, in a page with no token of its own, opens nothing.
    other = await page.context.browser.new_page()  # type: ignore[union-attr]
    try:
        await other.goto(given)
        await other.locator("#refused").wait_for(state="visible", timeout=SEEN_MS)
        assert await other.locator("#content > *").count() == 0
        await other.goto(f"{dash.base}/#code=made-up")
        await other.locator("#refused").wait_for(state="visible", timeout=SEEN_MS)
    finally:
        await other.close()
