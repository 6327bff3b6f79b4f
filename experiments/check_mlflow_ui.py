"""README's "Comparing models" steps, checked in a real browser against the installed MLflow.

Runs the smoke pipeline (two tiny models) and a two-job `-m` sweep over the same models into a
temporary folder with its own sqlite store, starts `mlflow ui` on a free port of 127.0.0.1, and walks
README's steps with headless Chromium (Playwright driving the system's /usr/bin/chromium; no browser is
downloaded and the page reaches nothing but 127.0.0.1):

  opens-on-runs     clicking the experiment in a fresh browser, then the sidebar's "Model training"
                    switch, shows the runs table (not the GenAI overview), and the browser remembers it
  direct-link       `#/experiments/<id>?workflowType=machine_learning` opens on the runs
  chart-models      Chart view, parent runs expanded: `xi_mean/<condition>` is one chart with a bar per
                    model run, the values the REST API returns
  chart-compare     the parent run's `compare/xi_mean/<condition>/<model>` keys: one chart per ranked
                    model, side by side in the section `compare/xi_mean/<condition>`, and none for the
                    reference model (graded on its own pseudo-labels, it is not ranked)
  colours           each model run is drawn in its figure colour (tag mlflow.runColor), distinct per model
  sweep-search      a search by the sweep's tag finds every run of the sweep (jobs and their model runs),
                    and the chart of those runs compares the sweep's models
  group-by-model    README's steps: Chart view, Group by the tag `model` with the parents folded: one chart
                    of `xi_mean/<condition>` with a bar per model, labelled, in distinct colours
  compare-page      ticking the model runs and clicking Compare opens the side-by-side run comparison
                    (its metrics table, below the long parameters table, is not looked for)

Prints PASS/FAIL per check (INFO for what was observed), saves screenshots to
experiments/figures/mlflow_*.png (1400x900), stops the server and exits 1 on any failure (or a check
that did not run). Not part of the test suite: `.ci/run` runs it after the tests, where Chromium and
Playwright install; by hand it needs `pip install playwright` and Chromium (Debian: `apt-get install chromium`).

    python experiments/check_mlflow_ui.py            # ~2.5 min on 2 busy cores
    python experiments/check_mlflow_ui.py --workdir /tmp/ui --keep   # reuse/keep the runs and store
"""
from __future__ import annotations

import argparse
import json
import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.parse
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EXPERIMENT = "smoke"
MODELS = ["tiny_segformer", "tiny_mask2former"]
CONDITION = "Night-EXTRASUNNY"
SWEEP = "ui_check_sweep"  # the sweep folder's name, hence its tag pairedgta.sweep
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]
VIEWPORT = {"width": 1400, "height": 900}
UI_WAIT_MS = 90_000  # the UI on a busy 2-core machine takes tens of seconds for its first page

results: list[tuple[str, bool]] = []
CHECKS = ("store", "opens-on-runs", "switch-remembered", "chart-compare", "chart-models", "colours", "sweep-search",
          "group-by-model", "compare-page", "direct-link")  # a check that never reported fails too


def report(name: str, ok: bool, detail: str) -> None:
    results.append((name, ok))
    print(f"{'PASS' if ok else 'FAIL'} {name}: {detail}", flush=True)


def info(text: str) -> None:
    print(f"INFO {text}", flush=True)


# -- the runs ---------------------------------------------------------------------------------------------
def pipeline(work: Path) -> None:
    common = [f"cache_dir={work / 'cache'}", f"tracking.uri=sqlite:///{work / 'mlflow.db'}",
              "plot.figures=[xi_models,xi_table]", "plot.formats=[png]"]
    jobs = [["+experiment=smoke", f"models=[{','.join(MODELS)}]", f"hydra.run.dir={work / 'runs' / 'single'}", *common],
            ["-m", "+experiment=smoke", f"model={','.join(MODELS)}", f"hydra.sweep.dir={work / 'multirun' / SWEEP}",
             *common]]
    for args in jobs:
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "pairedgta", *args], cwd=work, capture_output=True, text=True)
        if proc.returncode != 0:
            sys.exit(f"pipeline failed ({' '.join(args)}):\n{proc.stderr[-3000:]}")
        info(f"python -m pairedgta {' '.join(a for a in args if not a.startswith(('cache_dir', 'tracking', 'hydra')))}"
             f" ({time.perf_counter() - t0:.0f} s)")


# -- the server and its REST API --------------------------------------------------------------------------
def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    def __init__(self, db: Path, work: Path) -> None:
        self.port = free_port()
        self.base = f"http://127.0.0.1:{self.port}"
        env = {**os.environ, "MLFLOW_DISABLE_TELEMETRY": "true", "DO_NOT_TRACK": "true"}
        self.log = open(work / "mlflow_ui.log", "w")
        # README's command; its own process group, so that stopping it stops its workers and nothing else
        self.proc = subprocess.Popen([sys.executable, "-m", "mlflow", "ui", "--backend-store-uri", f"sqlite:///{db}", "--host", "127.0.0.1",
                                      "--port", str(self.port)], cwd=work, env=env, stdout=self.log,
                                     stderr=subprocess.STDOUT, start_new_session=True)

    def get(self, path: str, **params: str) -> dict:
        url = f"{self.base}/api/2.0/mlflow/{path}?{urllib.parse.urlencode(params)}"
        with urllib.request.urlopen(url, timeout=30) as r:
            return json.load(r)

    def post(self, path: str, body: dict) -> dict:
        req = urllib.request.Request(f"{self.base}/api/2.0/mlflow/{path}", data=json.dumps(body).encode(),
                                     headers={"Content-Type": "application/json"})
        with urllib.request.urlopen(req, timeout=30) as r:
            return json.load(r)

    def wait(self, work: Path, timeout_s: float = 240) -> dict:
        """The experiment, once the server answers: from this store (its artifacts lie under `work`)."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if self.proc.poll() is not None:
                sys.exit(f"mlflow ui exited ({self.proc.returncode}); see {self.log.name}")
            try:
                exp = self.get("experiments/get-by-name", experiment_name=EXPERIMENT)["experiment"]
            except OSError:
                time.sleep(1)
                continue
            if str(work) not in exp["artifact_location"]:
                sys.exit(f"port {self.port} answers for another store ({exp['artifact_location']})")
            return exp
        sys.exit(f"mlflow ui did not answer within {timeout_s:.0f} s; see {self.log.name}")

    def runs(self, experiment_id: str, filter_string: str = "") -> list[dict]:
        out = self.post("runs/search", {"experiment_ids": [experiment_id], "filter": filter_string,
                                        "max_results": 1000}).get("runs", [])
        for r in out:
            r["tags"] = {t["key"]: t["value"] for t in r["data"].get("tags", [])}
            r["metrics"] = {m["key"]: m["value"] for m in r["data"].get("metrics", [])}
            r["params"] = {p["key"]: p["value"] for p in r["data"].get("params", [])}
        return out

    def stop(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(5)
        self.log.close()


# -- the browser ------------------------------------------------------------------------------------------
def fresh_browser(pw, chromium: str, profile: Path):
    """A Chromium with an empty profile (nothing remembered) whose pages reach only 127.0.0.1."""
    ctx = pw.chromium.launch_persistent_context(str(profile), executable_path=chromium, headless=True,
                                                args=CHROMIUM_ARGS, viewport=VIEWPORT)
    ctx.route("**/*", lambda route: route.continue_() if urllib.parse.urlparse(route.request.url).hostname
              in ("127.0.0.1", None, "") else route.abort())
    page = ctx.pages[0] if ctx.pages else ctx.new_page()
    page.set_default_timeout(UI_WAIT_MS)
    return ctx, page


def runs_table_shown(page, timeout_ms: int = UI_WAIT_MS) -> bool:
    try:
        page.wait_for_selector("input[name=runs-view-mode]", state="attached", timeout=timeout_ms)
        page.get_by_text(re.compile(r"\d+ matching runs?")).first.wait_for(timeout=timeout_ms)
        return True
    except Exception:  # noqa: BLE001 - playwright's TimeoutError: not shown
        return False


def experiment_link(page):
    """The experiment's name in the experiments list (the sidebar may name it too, linking elsewhere)."""
    return page.get_by_test_id("experiment-list-item-link").filter(has_text=re.compile(rf"^{EXPERIMENT}$")).first


def matching_runs(page) -> int:
    text = page.get_by_text(re.compile(r"\d+ matching runs?")).first.inner_text()
    return int(re.search(r"(\d+)", text).group(1))


def dismiss_tip(page) -> None:
    """The GenAI overview's first-visit tip ("Detect Issues ... Got it") blocks every other click."""
    button = page.get_by_role("button", name="Got it")
    try:
        button.first.wait_for(timeout=5000)
        button.first.click()
        page.wait_for_timeout(800)
    except Exception:  # noqa: BLE001 - no tip
        pass


def close_assistant(page) -> None:
    button = page.locator('[data-component-id="mlflow.assistant.chat_panel.close"]')
    if button.count() and button.first.is_visible():
        button.first.click()


def settle(page, ms: int = 2500) -> None:
    """Give the UI time to fetch and draw (it polls the server, so the network never goes idle)."""
    page.wait_for_timeout(ms)


def expand_parents(page) -> None:
    """Unfold every parent run (a click on a parent that is open already folds it: then click again)."""
    buttons = page.locator('[data-component-id$="runnamecellrenderer.tsx_46"]')
    rows = page.get_by_test_id("experiment-view-table-run-color")
    for i in range(buttons.count()):
        before = rows.count()
        buttons.nth(i).click()
        page.wait_for_timeout(600)
        if rows.count() < before:
            buttons.nth(i).click()
            page.wait_for_timeout(600)


def view_mode(page, mode: str) -> None:
    page.locator(f"label:has(input[name=runs-view-mode][value={mode}])").click()
    settle(page)


def search_runs(page, text: str) -> None:
    box = page.get_by_test_id("search-box")
    box.fill(text)
    box.press("Enter")
    settle(page, 2500)


def group_by(page, tag: str) -> None:
    """The runs list's "Group by" control, the tag `tag` ticked."""
    page.get_by_role("button", name=re.compile("Group by")).first.click()
    page.wait_for_timeout(1000)
    page.get_by_role("menuitemcheckbox", name=tag, exact=True).first.click()
    page.wait_for_timeout(800)
    page.keyboard.press("Escape")
    settle(page)


def chart_card(page, title: str):
    return page.locator(f'[data-testid=experiment-view-compare-runs-card]:has(h4[title="{title}"])')


def show_section(page, name: str) -> None:
    header = page.get_by_test_id("experiment-view-compare-runs-section-header").filter(
        has_text=re.compile(rf"^{re.escape(name)}\s*\(\d+\)"))
    header.first.scroll_into_view_if_needed()
    page.wait_for_timeout(1500)


def bar_colours(card) -> list[str]:
    fills = card.locator("g.bars path, g.trace.bars path").evaluate_all(
        "els => els.map(e => getComputedStyle(e).fill)")
    out = []
    for f in fills:
        m = re.match(r"rgba?\((\d+), (\d+), (\d+)", f)
        if m:
            out.append("#%02x%02x%02x" % tuple(int(x) for x in m.groups()))
    return out


def shot(page, out: Path, name: str) -> Path:
    path = out / f"mlflow_{name}.png"
    page.screenshot(path=str(path))
    return path


# -- the checks -------------------------------------------------------------------------------------------
def check(server: Server, exp: dict, work: Path, out: Path, chromium: str) -> None:
    from playwright.sync_api import sync_playwright

    import mlflow

    from pairedgta.figures.common import model_color
    from pairedgta.tracking.naming import RUN_COLOR_TAG, SWEEP_TAG
    from matplotlib.colors import to_hex

    eid = exp["experiment_id"]
    runs = server.runs(eid)
    parents = [r for r in runs if "mlflow.parentRunId" not in r["tags"]]
    model_runs = [r for r in runs if "mlflow.parentRunId" in r["tags"]]
    single = [r for r in parents if SWEEP_TAG not in r["tags"]]
    sweep_runs = server.runs(eid, f"tags.`{SWEEP_TAG}` = '{SWEEP}'")
    kind = {t["key"]: t["value"] for t in exp.get("tags", [])}.get("mlflow.experimentKind")
    info(f"mlflow {mlflow.__version__}; store: {len(parents)} parent runs, {len(model_runs)} model runs; "
         f"experiment tag mlflow.experimentKind={kind}")
    main = single[0]
    main_models = {r["tags"]["model"]: r for r in model_runs if r["tags"]["mlflow.parentRunId"] == main["info"]["run_id"]}
    key = f"xi_mean/{CONDITION}"
    want = {m: main_models[m]["metrics"].get(key, float("nan")) for m in MODELS}
    # the reference model is graded on its own pseudo-labels: not ranked, so the parent carries no
    # compare/xi_mean key of it (pairedgta/figures/comparison.py); its model run keeps its xi_mean
    reference = main["params"].get("reference_model")
    ranked = [m for m in MODELS if m != reference]
    compare_keys = {m: f"compare/xi_mean/{CONDITION}/{m}" for m in ranked}
    unranked_key = f"compare/xi_mean/{CONDITION}/{reference}"
    ok = (set(main_models) == set(MODELS) and reference in MODELS and bool(ranked)
          and all(k in main["metrics"] for k in compare_keys.values()) and unranked_key not in main["metrics"]
          and all(key in main_models[m]["metrics"] for m in MODELS))
    report("store", ok, f"parent run '{main['info']['run_name']}' has {', '.join(compare_keys.values())} and, "
           f"the reference {reference} unranked, {'not ' if unranked_key not in main['metrics'] else ''}{unranked_key}; "
           f"its model runs have {key} = " + ", ".join(f"{m} {v:.3f}" for m, v in want.items()))

    # the browsers close (playwright's exit) before their profiles go, also when stopped part-way
    with tempfile.TemporaryDirectory(dir=work, ignore_cleanup_errors=True) as profiles, sync_playwright() as pw:
        # 1. README: click the experiment (a fresh browser: nothing remembered), then Model training
        ctx, page = fresh_browser(pw, chromium, Path(profiles) / "a")
        page.goto(f"{server.base}/#/experiments")
        experiment_link(page).click()
        on_runs = runs_table_shown(page, 20_000)
        settle(page)
        landed = urllib.parse.unquote(page.url.split("#", 1)[-1])
        info(f"a fresh browser clicking the experiment lands on {landed.split('&')[0]} "
             f"({'the runs table' if on_runs else 'the GenAI overview' if '/overview' in landed else 'not the runs'})")
        if not on_runs:
            shot(page, out, "opens_genai")
        dismiss_tip(page)
        page.get_by_text("Model training", exact=True).first.click()
        shown = runs_table_shown(page)
        settle(page)
        close_assistant(page)
        count = matching_runs(page) if shown else -1
        report("opens-on-runs", shown and count == len(runs),
               f"after the sidebar switch 'Model training': the runs table, {count} matching runs (REST: {len(runs)})")
        page.goto(f"{server.base}/#/experiments")
        experiment_link(page).click()
        again = runs_table_shown(page, 30_000)
        report("switch-remembered", again, "clicking the experiment again in the same browser opens the runs")

        # 2. Chart view with the parent runs expanded: one chart of xi_mean/<condition>, a bar per model run
        settle(page)
        close_assistant(page)
        expand_parents(page)
        settle(page)
        swatches = page.get_by_test_id("experiment-view-table-run-color")
        rows = [(swatches.nth(i).inner_text().strip(), swatches.nth(i).locator("xpath=ancestor::div[@role='row'][1]")
                 .inner_text()) for i in range(swatches.count())]
        info(f"runs table after expanding: {len(rows)} rows")
        shot(page, out, "runs")
        view_mode(page, "CHART")
        page.get_by_placeholder("Search metric charts").fill(key)
        settle(page)
        # the parent's per-model keys first: one section, one chart per ranked model, none for the reference
        show_section(page, f"compare/xi_mean/{CONDITION}")
        cards = {m: chart_card(page, k) for m, k in compare_keys.items()}
        found = {m: c.count() == 1 for m, c in cards.items()}
        texts = {m: c.first.inner_text() if found[m] else "" for m, c in cards.items()}
        values_ok = all(f"{main['metrics'][compare_keys[m]]:.2f}" in texts[m] for m in ranked)
        unranked_charts = chart_card(page, unranked_key).count()
        report("chart-compare", all(found.values()) and values_ok and unranked_charts == 0,
               f"section compare/xi_mean/{CONDITION}: one chart per ranked model ({', '.join(m for m in ranked if found[m])}), "
               f"each a bar per parent run, values as in REST; {unranked_charts} chart(s) of the reference {reference}")
        # collapse the other sections so the per-model-run chart is on screen with the parent's
        for header_text in (f"table/generated/xi_mean/{CONDITION}",):
            header = page.get_by_test_id("experiment-view-compare-runs-section-header").filter(has_text=header_text)
            if header.count():
                header.first.click()  # folds the section
                page.wait_for_timeout(800)
        show_section(page, "xi_mean")
        card = chart_card(page, key)
        card.first.scroll_into_view_if_needed()
        page.wait_for_timeout(1500)
        text = card.first.inner_text() if card.count() else ""
        names = {m: main_models[m]["info"]["run_name"] for m in MODELS}
        in_chart = {m: names[m] in text and f"{want[m]:.2f}" in text for m in MODELS}
        report("chart-models", card.count() == 1 and all(in_chart.values()),
               f"chart '{key}': a bar per model run (" + ", ".join(f"{m} {want[m]:.2f}" for m in MODELS if in_chart[m])
               + ") in one chart")
        page.mouse.wheel(0, -200)
        page.wait_for_timeout(800)
        shot(page, out, "chart")

        # 3. colours: each model run in its figure colour, one colour per model
        expected = {m: to_hex(model_color(m)) for m in MODELS}
        tagged = {m: main_models[m]["tags"].get(RUN_COLOR_TAG) for m in MODELS}
        table_colours = {m: {c for c, row in rows if names[m] in row and c.startswith("#")} for m in MODELS}
        bars = bar_colours(card.first) if card.count() else []
        distinct = len(set(expected.values())) == len(MODELS)
        ok = distinct and tagged == expected and all(expected[m] in table_colours[m] for m in MODELS) \
            and all(expected[m] in bars for m in MODELS)
        report("colours", ok, ", ".join(f"{m} {tagged[m]} (figures {expected[m]}, table {sorted(table_colours[m])})"
                                        for m in MODELS) + f"; chart bars {sorted(set(bars))}")

        # 4. the sweep: a search by its tag finds its jobs and their model runs; their chart compares the models
        view_mode(page, "TABLE")
        search_runs(page, f"tags.`{SWEEP_TAG}` = '{SWEEP}'")
        close_assistant(page)
        count = matching_runs(page)
        sweep_models = sorted(r["tags"].get("model", "") for r in sweep_runs if "mlflow.parentRunId" in r["tags"])
        expected_runs = [r for r in runs if r["tags"].get(SWEEP_TAG) == SWEEP
                         or any(p["info"]["run_id"] == r["tags"].get("mlflow.parentRunId")
                                for p in parents if p["tags"].get(SWEEP_TAG) == SWEEP)]
        expand_parents(page)
        view_mode(page, "CHART")
        page.get_by_placeholder("Search metric charts").fill(key)
        settle(page)
        show_section(page, "xi_mean")
        card = chart_card(page, key)
        card.first.scroll_into_view_if_needed()
        page.wait_for_timeout(1500)
        text = card.first.inner_text() if card.count() else ""
        sweep_names = [r["info"]["run_name"] for r in sweep_runs if "mlflow.parentRunId" in r["tags"]]
        charted = all(n in text for n in sweep_names) and len(sweep_names) == len(MODELS)
        report("sweep-search", count == len(sweep_runs) == len(expected_runs) and sweep_models == sorted(MODELS) and charted,
               f"tags.`{SWEEP_TAG}` = '{SWEEP}': {count} matching runs in the UI, {len(sweep_runs)} by REST, "
               f"{len(expected_runs)} runs in the sweep (jobs and model runs; model runs: {', '.join(sweep_models) or 'none'}); "
               f"chart '{key}' of the result has a bar per model: {charted}")
        shot(page, out, "sweep_search")

        # 5. README's steps: Group by the model tag, parents folded: one chart, a bar per model
        search_runs(page, "")
        group_by(page, "model")
        groups = sorted(re.findall(r"Group: ([^\n]+)", page.inner_text("body")))
        view_mode(page, "CHART")
        page.get_by_placeholder("Search metric charts").fill(key)
        settle(page)
        show_section(page, "xi_mean")
        card = chart_card(page, key)
        card.first.scroll_into_view_if_needed()
        page.wait_for_timeout(1500)
        text = card.first.inner_text() if card.count() else ""
        bars = bar_colours(card.first) if card.count() else []
        labelled = {m: m in text.splitlines() and f"{want[m]:.2f}" in text for m in MODELS}
        report("group-by-model", card.count() == 1 and all(labelled.values()) and groups == sorted(MODELS)
               and len(set(bars)) == len(MODELS),
               f"Group by model: groups {', '.join(groups)}; chart '{key}' has a bar per model ("
               + ", ".join(f"{m} {want[m]:.2f}" for m in MODELS if labelled[m]) + f"), colours {sorted(set(bars))}")
        shot(page, out, "group_by_model")
        ctx.close()

        # 6. Compare: tick the model runs, click Compare (a fresh browser: no grouping remembered)
        ctx, page = fresh_browser(pw, chromium, Path(profiles) / "c")
        page.goto(f"{server.base}/#/experiments/{eid}?workflowType=machine_learning")
        runs_table_shown(page)
        settle(page)
        close_assistant(page)
        expand_parents(page)
        settle(page, 1000)
        boxes = page.locator('input[aria-label^="Press Space to toggle row selection"]')
        picked = 0
        for i in range(boxes.count()):
            row = boxes.nth(i).locator("xpath=ancestor::div[@role='row'][1]").inner_text()
            if any(names[m] in row for m in MODELS) and picked < len(MODELS):
                boxes.nth(i).click(force=True)
                picked += 1
                page.wait_for_timeout(300)
        page.get_by_role("button", name="Compare").click()
        page.get_by_text(re.compile(r"Comparing \d+ Runs")).first.wait_for()
        settle(page)
        body = page.inner_text("body")
        heading = re.search(r"Comparing \d+ Runs[^\n]*", body)
        compared = int(re.search(r"\d+", heading.group(0)).group(0)) if heading else 0
        # a sweep job's parent run has its model run's name; ticking it ticks its model run too
        report("compare-page", compared >= len(MODELS) and all(names[m] in body for m in MODELS),
               f"'{heading.group(0) if heading else 'no comparison'}', the model runs side by side: "
               f"{[names[m] in body for m in MODELS]}")
        ctx.close()

        # 7. a link straight to the runs, in another fresh browser
        ctx, page = fresh_browser(pw, chromium, Path(profiles) / "b")
        page.goto(f"{server.base}/#/experiments/{eid}?workflowType=machine_learning")
        report("direct-link", runs_table_shown(page), f"#/experiments/{eid}?workflowType=machine_learning opens on the runs")
        ctx.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workdir", type=Path, default=None, help="runs, cache and store (default: a temporary folder)")
    ap.add_argument("--keep", action="store_true", help="keep --workdir's runs for the next call (skips the pipeline)")
    ap.add_argument("--out", type=Path, default=ROOT / "experiments" / "figures", help="where the screenshots go")
    ap.add_argument("--chromium", default="/usr/bin/chromium")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    # a CI's `timeout` (SIGTERM) unwinds: the browser closes and the server's process group is stopped
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(143))
    with tempfile.TemporaryDirectory(prefix="pgta-mlflow-ui-") as tmp:
        work = (args.workdir or Path(tmp)).resolve()
        work.mkdir(parents=True, exist_ok=True)
        db = work / "mlflow.db"
        if not (args.keep and db.exists()):
            pipeline(work)
        server = Server(db, work)
        try:
            exp = server.wait(work)
            check(server, exp, work, args.out, args.chromium)
        finally:
            server.stop()
    failed = [name for name, ok in results if not ok] + [f"{name} (not run)" for name in CHECKS
                                                          if name not in {n for n, _ in results}]
    print(f"{sum(ok for _, ok in results)}/{len(CHECKS)} checks passed" + (f"; failed: {', '.join(failed)}" if failed else ""))
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
