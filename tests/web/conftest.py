"""Fixtures of the dashboard tests: fast certified gains, and headless Chromium (Debian's, driven by Playwright).

Browser tests skip, saying why, only when chromium is not installed on a developer's machine; under CI
(the CI environment variable is set) a missing chromium fails them: .ci/install-system-deps installs it.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator
from typing import Any

import pytest

from synth.design import synthesize
from synth.gains import ObserverGains
from synth.options import DesignOptions
from tests.service.helpers import FAST_DESIGN
from tests.web.helpers import CHROMIUM_ARGS, OUTPUT_DIR, chromium_executable

VIEWPORT = {"width": 1440, "height": 900}


@pytest.fixture(scope="session")
def fast_gains() -> ObserverGains:
    return synthesize(options=DesignOptions(**FAST_DESIGN))


@pytest.fixture(scope="session")
def chromium() -> str:
    path = chromium_executable()
    if path is None:
        if os.environ.get("CI"):
            pytest.fail("chromium is not installed: CI must install it (.ci/install-system-deps)")
        pytest.skip("Debian's chromium is not installed (apt-get install chromium): browser tests skipped")
    return path


@pytest.fixture(scope="module")
def browser(chromium: str) -> Iterator[Any]:
    """One Chromium per test module: Playwright's sync API holds an asyncio loop in the main thread while it
    runs, so it must be stopped before tests that start their own loop (asyncio.run)."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=chromium, headless=True, args=CHROMIUM_ARGS)
        try:
            yield browser
        finally:
            browser.close()


class PageProblems(list[str]):
    """Console errors and uncaught exceptions of a page (a CSP violation is a console error)."""

    def __init__(self) -> None:
        super().__init__()
        self.allowed: list[re.Pattern[str]] = []

    def allow(self, pattern: str) -> None:
        """A problem the test provokes on purpose (a refused request is logged as a console error)."""
        self.allowed.append(re.compile(pattern))

    def unexpected(self) -> list[str]:
        return [p for p in self if not any(a.search(p) for a in self.allowed)]


@pytest.fixture
def browser_context(browser: Any) -> Iterator[Any]:
    context = browser.new_context(viewport=VIEWPORT)
    try:
        yield context
    finally:
        context.close()


def watch(page: Any, problems: PageProblems | None = None) -> PageProblems:
    problems = PageProblems() if problems is None else problems
    page.on("console", lambda m: problems.append(f"console {m.type}: {m.text}") if m.type == "error" else None)
    page.on("pageerror", lambda e: problems.append(f"uncaught: {e}"))
    return problems


@pytest.fixture
def page_problems() -> PageProblems:
    return PageProblems()


@pytest.fixture
def page(browser_context: Any, page_problems: PageProblems) -> Iterator[Any]:
    """A fresh page; the test fails if the page logged an error or threw that the test did not provoke."""
    page = browser_context.new_page()
    watch(page, page_problems)
    yield page
    assert not page_problems.unexpected(), "\n".join(page_problems.unexpected())


@pytest.fixture(scope="session")
def output_dir() -> Any:
    OUTPUT_DIR.mkdir(parents=True, exist_ok=True)
    return OUTPUT_DIR
