"""The console in a real browser (Debian's chromium driven by Playwright) against a real
``loopnet serve`` and a real retraining worker, on Gardens Point frames.

The tests run in order on one service: an admin creates an atlas, robots' frames arrive
through the API, then each page is used as its role allows. Each page's screenshot is taken;
with ``LOOPNET_UPDATE_SCREENSHOTS=1`` it is saved under docs/screenshots/ (the docs show them),
otherwise in a temporary folder, so a test run leaves the tracked tree as it found it.
"""

from __future__ import annotations

import csv
import itertools
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from service.client import LoopNetClient, LoopNetError
from tests.conftest import DATA_DIR, ROOT
from tests.jobs.test_retraining_jobs import start_worker, stop_worker
from tests.processes import create_token, service_env, serving

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--no-first-run",
    "--disable-sync",
]
SCREENSHOTS = (
    ROOT / "docs" / "screenshots"
    if os.environ.get("LOOPNET_UPDATE_SCREENSHOTS") == "1"
    else Path(tempfile.gettempdir()) / "loopnet-console-screenshots"
)
COHOG = DATA_DIR / "gardenspoint_cohog200"
# places far apart along the route, so no two look alike; two robots, two submaps each
ROUTE = {"husky-1": (0, 25, 50, 75, 100, 125), "husky-2": (140, 160, 180, 195)}
SUBMAPS_OF = {"husky-1": ("campus-a", "campus-b"), "husky-2": ("campus-c", "campus-d")}
ATLAS = "gardens"


def _need_browser() -> Any:
    reason = None
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        reason = "the playwright Python package is not installed"
    if reason is None and not CHROMIUM.exists():
        reason = f"no chromium at {CHROMIUM} (apt-get install chromium)"
    if reason is not None:
        if os.environ.get("LOOPNET_REQUIRE_SERVICES") == "1":
            pytest.fail(f"{reason}, and LOOPNET_REQUIRE_SERVICES=1")
        pytest.skip(reason)
    return sync_playwright


def cohog(place: int, side: str) -> Path:
    rows = list(csv.DictReader((COHOG / "gt.csv").open()))
    return COHOG / rows[place][side]


class Console:
    """The running service, its keys and frame ids, and one browser."""

    def __init__(self, url: str, tokens: dict[str, str], browser: Any) -> None:
        self.url, self.tokens, self.browser = url, tokens, browser
        self.frames: dict[int, int] = {}  # place -> frame id
        self.errors: list[str] = []

    def page(self, role: str) -> Any:
        """A fresh tab signed in with the key of ``role``."""
        page = self.watched_page()
        page.goto(self.url + "/")
        page.fill("#login-key", self.tokens[role])
        page.click("#login button[type=submit]")
        page.wait_for_selector("#who-role:not(:empty)")
        assert page.text_content("#who-role") == role
        return page

    def watched_page(self) -> Any:
        """A fresh tab whose script errors and Content-Security-Policy refusals are recorded
        (issue 24: the pages run under the service's policy)."""
        page = self.browser.new_page(viewport={"width": 1280, "height": 860})
        page.on("pageerror", lambda exc: self.errors.append(str(exc)))
        page.on(
            "console",
            lambda msg: (
                self.errors.append(msg.text) if "Content Security Policy" in msg.text else None
            ),
        )
        return page

    def client(self, role: str = "admin") -> LoopNetClient:
        return LoopNetClient(self.url, api_key=self.tokens[role])


def shoot(page: Any, name: str, *, mask: tuple[str, ...] = ()) -> None:
    """Save the page under :data:`SCREENSHOTS` (``mask``: selectors painted over, e.g. tokens)."""
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    masked = [page.locator(selector) for selector in mask]
    page.screenshot(
        path=str(SCREENSHOTS / f"{name}.png"), full_page=True, mask=masked, mask_color="#101828"
    )


def thumbnails_loaded(page: Any, selector: str) -> None:
    page.wait_for_function(
        """sel => { const imgs = [...document.querySelectorAll(sel)];
                     return imgs.length > 0 && imgs.every(i => i.complete && i.naturalWidth > 0); }""",
        arg=selector,
    )


@pytest.fixture(scope="module")
def console(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Console]:
    sync_playwright = _need_browser()
    data = tmp_path_factory.mktemp("console") / "data"
    tokens = {role: create_token(data, f"{role}-key", role) for role in ("admin", "operator")}
    tokens["robot"] = create_token(data, "husky-2", "robot")  # a robot key is its robot
    env = service_env(data, LOOPNET_AUTH="required", LOOPNET_TORCH_THREADS="1")
    with serving(env) as url:
        worker = start_worker(env)
        try:
            with sync_playwright() as playwright:
                browser = playwright.chromium.launch(
                    executable_path=str(CHROMIUM), args=CHROMIUM_ARGS
                )
                try:
                    yield Console(url, tokens, browser)
                finally:
                    browser.close()
        finally:
            stop_worker(worker)


def test_admin_creates_an_atlas_and_sees_each_robots_trajectory(console: Console) -> None:
    page = console.page("admin")
    page.fill("[data-testid=create-atlas] input[name=name]", ATLAS)
    page.fill("[data-testid=create-atlas] input[name=description]", "Gardens Point, QUT")
    page.click("[data-testid=create-atlas] button")
    page.wait_for_selector(f"[data-testid=atlas-row-{ATLAS}]")

    with console.client() as loopnet:  # the robots' frames arrive through the API
        for robot, places in ROUTE.items():
            for submap in SUBMAPS_OF[robot]:
                loopnet.create_submap(ATLAS, submap)
            for i, place in enumerate(places):
                frame = loopnet.add_frame(
                    ATLAS,
                    cohog(place, "ref"),
                    submap=SUBMAPS_OF[robot][i * 2 // len(places)],
                    robot_id=robot,
                    timestamp=1000.0 + place,
                    pose={"rotation": [1, 0, 0, 0], "translation": [place * 0.5, 0.0, 0.0]},
                    intrinsics={"fx": 90.0, "fy": 90.0, "cx": 49.5, "cy": 28.0},
                )
                console.frames[place] = frame.frame_id

    page.reload()
    row = page.wait_for_selector(f"[data-testid=atlas-row-{ATLAS}]")
    text = row.text_content() or ""
    assert "10" in text and "husky-1, husky-2" in text and "v1" in text
    assert "uncalibrated" in text  # 10 frames: below the first calibration milestone
    shoot(page, "atlases")

    row.click()
    page.wait_for_selector("[data-testid=strip-husky-1]")
    thumbnails_loaded(page, "[data-testid=thumb] img")
    assert page.locator("[data-testid=strip-husky-1] [data-testid=thumb]").count() == 6
    assert page.locator("[data-testid=strip-husky-2] [data-testid=thumb]").count() == 4
    page.locator("[data-testid=strip-husky-1] [data-testid=thumb]").nth(2).click()
    assert "t 25.000, 0.000, 0.000" in (page.text_content("[data-testid=pose]") or "")  # place 50
    assert "fx 90" in (page.text_content("[data-testid=intrinsics]") or "")
    page.click("[data-testid=show-keypoints]")
    page.wait_for_selector("[data-testid=keypoints] circle")
    assert page.locator("[data-testid=keypoints] circle").count() > 20
    shoot(page, "atlas")
    page.close()


def test_query_page_finds_the_place(console: Console) -> None:
    page = console.page("robot")
    page.click("nav a[data-page=query]")
    page.set_input_files("[data-testid=query-file]", str(cohog(75, "query")))
    page.wait_for_selector("[data-testid=decision]")
    assert page.text_content("[data-testid=best-frame]") == str(console.frames[75])
    assert page.text_content("[data-testid=best-submap]") == "campus-b"
    with console.client("robot") as husky2:  # the page shows the API's own decision and why
        answer = husky2.query(ATLAS, cohog(75, "query"))
    assert answer.match is not None and answer.match.inliers is not None
    expected = {"loop": "loop closure", "candidate": "candidate (not a loop yet)"}
    assert page.text_content("[data-testid=decision]") == expected.get(answer.status, "new place")
    why = page.text_content("[data-testid=why]") or ""
    assert answer.decision is not None and answer.decision.loop_probability is not None
    assert f"{answer.match.inliers} inliers" in why
    assert f"loop_probability {answer.decision.loop_probability:.3f} (a loop needs 0.98)" in why
    thumbnails_loaded(page, "[data-testid=candidate] img")
    assert page.locator("[data-testid=candidate]").count() == 5
    if answer.match.scale is not None:  # where the match was taken, as the re-rank read it
        best = page.locator("[data-testid=candidate]").first.text_content() or ""
        assert f"zoom {answer.match.scale:.2f}" in best
    shoot(page, "query")
    page.close()


def test_loop_closures_graph_and_one_closure_side_by_side(console: Console) -> None:
    intrinsics = {"fx": 90.0, "fy": 90.0, "cx": 49.5, "cy": 28.0}
    inliers = {}
    with console.client("robot") as husky2:  # husky-2 revisits the places husky-1 mapped
        for place in ROUTE["husky-1"]:
            answer = husky2.query(ATLAS, cohog(place, "query"), intrinsics=intrinsics)
            assert answer.match is not None and answer.match.frame_id == console.frames[place]
            inliers[place] = answer.match.inliers or 0
        # ... and observes the place it recognised best as its new keyframe: the frame is kept,
        # so that closure's matches can be drawn
        observed = max(inliers, key=inliers.__getitem__)
        seen = husky2.observe(
            ATLAS,
            cohog(observed, "query"),
            submap=SUBMAPS_OF["husky-2"][1],
            robot_id="husky-2",
            intrinsics=intrinsics,
        )
        assert seen.loop_closure and seen.match is not None
        assert seen.match.frame_id == console.frames[observed]
        found = husky2.loop_closures(ATLAS)  # one per verified loop closure, newest first
        drawn = husky2.loop_closure_matches(ATLAS, found[0].id)
    closed = len(found)
    assert closed >= 2, "husky-2 should recognise at least one of husky-1's places"
    assert found[0].source == "observe"
    page = console.page("operator")
    page.click("nav a[data-page=closures]")
    page.wait_for_selector("[data-testid=closure-graph] line", state="attached")
    assert page.locator("[data-testid=edge-count]").all_text_contents() == [str(closed)]
    assert page.locator("tr[data-testid^=closure-]").count() == closed
    page.locator(f"tr[data-testid=closure-{found[-1].id}]").click()  # a query's: no matches
    page.wait_for_selector("[data-testid=relative-pose]")
    thumbnails_loaded(page, "[data-testid=closure-detail] img")
    assert "R q" in (page.text_content("[data-testid=relative-pose]") or "")
    assert page.locator("[data-testid=closure-matches]").count() == 0

    page.locator(f"tr[data-testid=closure-{found[0].id}]").click()  # the observation's
    page.wait_for_selector("[data-testid=closure-matches] image[data-loaded]", state="attached")
    page.wait_for_function(
        "document.querySelectorAll('[data-testid=closure-matches] image[data-loaded]').length == 2"
    )
    lines = page.locator("[data-testid=closure-matches] line")
    assert lines.count() == len(drawn.pairs) > 0
    summary = page.text_content("[data-testid=match-summary]") or ""
    assert summary.startswith(f"{lines.count()} inliers"), summary
    assert "R q" in (page.text_content("[data-testid=relative-pose]") or "")
    shoot(page, "loop-closures")
    page.close()


def test_operator_retrains_watches_progress_and_rolls_back(console: Console) -> None:
    page = console.page("operator")
    page.click("nav a[data-page=jobs]")
    page.wait_for_selector("[data-testid=start-job]")
    page.click("[data-testid=start-job] button")
    page.wait_for_selector("[data-testid=job-status]")
    seen = set()
    for _ in range(300):  # the page polls the job every second
        seen.add(page.text_content("[data-testid=job-progress]"))
        if page.text_content("[data-testid=job-status]") in ("succeeded", "failed", "cancelled"):
            break
        page.wait_for_timeout(300)
    assert page.text_content("[data-testid=job-status]") == "succeeded", seen
    page.wait_for_selector("[data-testid=job-progress]:has-text('100%')")
    page.wait_for_selector("[data-testid=model-v2]")
    message = page.text_content("[data-testid=job-message]") or ""
    if "was not activated" in message:  # the gate's call (it differs between CPUs on 10 frames)
        assert page.locator("[data-testid=model-v1] [data-testid=active-version]").count() == 1
        page.click("[data-testid=activate-v2]")  # the operator may still choose it
    else:
        assert "is active" in message, message
    page.wait_for_selector("[data-testid=model-v2] [data-testid=active-version]")
    shoot(page, "jobs")

    page.click("[data-testid=activate-v1]")  # roll back
    page.wait_for_selector("[data-testid=model-v1] [data-testid=active-version]")
    with console.client("operator") as loopnet:
        assert [v.version for v in loopnet.list_models(ATLAS) if v.is_active] == [1]
    page.click("[data-testid=activate-v2]")  # and forward again
    page.wait_for_selector("[data-testid=model-v2] [data-testid=active-version]")
    page.close()


def test_operator_labels_lists_and_deletes_revisit_pairs(console: Console) -> None:
    with console.client("operator") as loopnet:  # the closures test's observation gave one
        observed = loopnet.list_pairs(ATLAS)
    assert [p.source for p in observed] == ["observe"]
    page = console.page("operator")
    page.click("nav a[data-page=pairs]")
    page.wait_for_selector(f"[data-testid=pair-{observed[0].id}]")
    thumbnails_loaded(page, "[data-testid=pairs] img")
    a, b = console.frames[0], console.frames[25]
    page.fill("[data-testid=label-pair] input[name=frame_id]", str(a))
    page.fill("[data-testid=label-pair] input[name=other_frame_id]", str(b))
    page.click("[data-testid=label-pair] button")
    page.wait_for_selector("[data-testid=pairs-notice]:has-text('labelled')")
    with console.client("operator") as loopnet:
        labelled = [p for p in loopnet.list_pairs(ATLAS) if p.source == "operator"]
    assert [(p.frame_id, p.other_frame_id) for p in labelled] == [(a, b)]
    row = page.wait_for_selector(f"[data-testid=pair-{labelled[0].id}]")
    assert "operator" in (row.text_content() or "") and f"frame {a}" in (row.text_content() or "")
    thumbnails_loaded(page, "[data-testid=pairs] img")
    shoot(page, "pairs")
    for frames, expected in (((b, a), "409: frames"), ((a, 10**6), "404: ")):  # API errors shown
        page.fill("[data-testid=label-pair] input[name=frame_id]", str(frames[0]))
        page.fill("[data-testid=label-pair] input[name=other_frame_id]", str(frames[1]))
        page.click("[data-testid=label-pair] button")
        page.wait_for_selector(f"[data-testid=pairs-error] [role=alert]:has-text('{expected}')")
    page.once("dialog", lambda dialog: dialog.accept())
    page.click(f"[data-testid=pair-{labelled[0].id}] [data-testid=delete-pair]")
    page.wait_for_selector(f"[data-testid=pair-{labelled[0].id}]", state="detached")
    page.click("[data-testid=adapt-button]")  # one pair left: the API refuses, and says why
    refused = page.wait_for_selector("[data-testid=pairs-error] [role=alert]:has-text('422')")
    assert "1 revisit pair(s)" in (refused.text_content() or ""), refused.text_content()
    assert "adaptation needs at least 10" in (refused.text_content() or "")
    with console.client("operator") as loopnet:
        assert [p.id for p in loopnet.list_pairs(ATLAS)] == [observed[0].id]
        assert all(job.kind != "adapt" for job in loopnet.list_jobs(ATLAS))
        # enough labelled pairs (right or not): the page queues the job
        for first, second in list(itertools.combinations(ROUTE["husky-1"], 2))[:9]:
            loopnet.label_pair(ATLAS, console.frames[first], console.frames[second])
    page.click("[data-testid=adapt-button]")
    queued = page.wait_for_selector("[data-testid=adapt-queued]").text_content() or ""
    with console.client("operator") as loopnet:
        job = loopnet.wait_job(ATLAS, int(queued.split()[2]), timeout=120)
    assert job.kind == "adapt" and job.status in ("succeeded", "failed"), job
    assert job.message.startswith("model version") or "usable revisit pair" in job.message, job
    page.close()


def test_admin_creates_and_revokes_a_key(console: Console) -> None:
    page = console.page("admin")
    page.click("nav a[data-page=keys]")
    page.fill("[data-testid=create-key] input[name=name]", "husky-3")
    page.select_option("[data-testid=create-key] select[name=role]", "robot")
    page.fill("[data-testid=create-key] input[name=atlases]", ATLAS)
    page.click("[data-testid=create-key] button")
    token = (page.text_content("[data-testid=new-token]") or "").strip()
    assert token.startswith("lnk_")
    with LoopNetClient(console.url, api_key=token) as husky3:
        assert husky3.whoami().name == "husky-3"
    row = page.wait_for_selector("[data-testid=key-husky-3]")
    assert "active" in (row.text_content() or "")
    shoot(page, "keys", mask=("[data-testid=new-token]",))  # never commit a token
    page.once("dialog", lambda dialog: dialog.accept())
    page.click("[data-testid=key-husky-3] [data-testid=revoke-key]")
    page.wait_for_selector("[data-testid=key-husky-3] [data-testid=key-state]:has-text('revoked')")
    with LoopNetClient(console.url, api_key=token) as husky3, pytest.raises(LoopNetError) as e:
        husky3.whoami()
    assert e.value.status == 401
    page.close()


def test_a_robot_key_sees_no_operator_or_admin_controls(console: Console) -> None:
    page = console.page("robot")
    page.wait_for_selector(f"[data-testid=atlas-row-{ATLAS}]")
    for link in ("jobs", "pairs", "keys"):
        assert page.is_hidden(f"nav a[data-page={link}]")
    assert page.locator("[data-testid=create-atlas]").count() == 0
    for hidden in ("jobs", "pairs", "keys"):  # typed in by hand, the page falls back to the atlases
        page.goto(f"{console.url}/#/{hidden}")
        page.wait_for_selector(f"[data-testid=atlas-row-{ATLAS}]")
        assert page.get_attribute("#page", "data-page") == "atlases"
        assert (
            page.locator(
                "[data-testid=start-job], [data-testid=create-key], [data-testid=label-pair]"
            ).count()
            == 0
        )
    shoot(page, "robot-view")
    page.close()
    assert console.errors == []  # no script error on any page


def test_the_api_docs_work_under_their_policy(console: Console) -> None:
    """/docs (Swagger UI) and /redoc render the API under their Content-Security-Policy: the
    bundled scripts and the one inline start-up script run, nothing is refused."""
    page = console.watched_page()
    page.goto(console.url + "/docs")
    page.wait_for_selector('.opblock-summary-path[data-path="/v1/atlases/{atlas}/query"]')
    page.click('.opblock-summary-path[data-path="/v1/health"]')  # the interactive part works
    page.wait_for_selector("button.try-out__btn")
    page.goto(console.url + "/redoc")
    page.wait_for_selector('h1:has-text("LoopNet")', timeout=30_000)
    page.wait_for_selector('h2:has-text("Create an atlas")')  # the operations are listed
    page.close()
    # ReDoc's footer links Redocly's logo from its CDN: blocked, as every third-party load is
    refused = [e for e in console.errors if "https://cdn.redoc.ly/" not in e]
    assert refused == []


def test_chromium_is_the_debian_one() -> None:
    """The tests drive the system's chromium; Playwright's own browser download is not used."""
    _need_browser()
    assert shutil.which("chromium") == str(CHROMIUM) or CHROMIUM.exists()
