"""The docs read as a library's, with the measurements apart.

* The README is the user's door (at most 150 lines) and no user page runs past 400 lines.
* The README and Home (docs/index.md) list exactly the registered Gymnasium environments, the shipped
  models and every command, each list between ``<!-- envs -->``, ``<!-- models -->`` and
  ``<!-- commands -->`` markers, checked here against the registry, ``training.pretrained.names()``
  and the CLI's parser.
* User pages (docs/*.md but the changelog, and the README) hold no project bookkeeping: no goal met
  or missed, no machine conditions ("quiet", "beside a test run"), no lost runs or device time.
  Measurements with their hardware live in docs/results/, one page per study, each stating its
  hardware once (``**Hardware.**``).
* One word, one meaning: "certify", "certified" and "certificate" mean a formal proof; the statistical
  guarantee is a scenario bound, set or volume, on every page but the changelog (history).
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
README = ROOT / "README.md"
RESULTS = DOCS / "results"
#: every page a user reads for how-to (docs/api/ is generated from docstrings, the changelog is history)
USER_PAGES = sorted(p for p in DOCS.glob("*.md") if p.name != "changelog.md")
MAX_README_LINES = 150
MAX_PAGE_LINES = 400

#: wording of the project's own bookkeeping, which belongs in docs/results/ or the changelog
BOOKKEEPING = {
    "a numbered goal": re.compile(r"\bgoal\s*\d", re.I),
    "a goal met or missed": re.compile(r"\bgoals?\b[^.|\n]*(?:\n[^.|\n]*)?\b(?:met|missed|meets|misses)\b", re.I),
    "a quiet machine": re.compile(r"\bquiet\b", re.I),
    "a run beside a test run": re.compile(r"\bbeside (?:a|the) test", re.I),
    "a run beside other work": re.compile(r"\bbeside other (?:work|runs|processes)\b", re.I),
    "a busy machine": re.compile(
        r"\bmachine (?:was|is) (?:busy|loaded|shared)\b|\b(?:busy|loaded|shared) (?:\d-core )?machine\b", re.I
    ),
    "a lost run": re.compile(r"\blost with (?:its|their|that|the) (?:machine|session)\b", re.I),
    "device time": re.compile(r"\bdevice time\b", re.I),
}
#: the statistical guarantee named as a certificate
CERTIFIED_STATISTICS = re.compile(
    r"\bcertified\s+vol|\brobust\s+certified\b|\bstatistical\s+certificate|\bscenario\s+certif|"
    r"\bscenario\s+guarantee",
    re.I,
)


def bookkeeping(text: str) -> list[str]:
    """What the text says about the project's goals, its machines' load or its lost runs, one line each."""
    return [f"{what}: {m.group(0)!r}" for what, pattern in BOOKKEEPING.items() for m in pattern.finditer(text)]


def page_text(path: Path) -> str:
    return path.read_text(encoding="utf-8")


# ---------------------------------------------------------------------- sizes
def test_the_readme_is_a_door():
    lines = page_text(README).splitlines()
    assert len(lines) <= MAX_README_LINES, f"README.md has {len(lines)} lines; measurements belong in docs/results/"


@pytest.mark.parametrize("page", USER_PAGES, ids=lambda p: p.name)
def test_user_pages_stay_short(page):
    lines = page_text(page).splitlines()
    assert len(lines) <= MAX_PAGE_LINES, f"docs/{page.name} has {len(lines)} lines; move measurements to docs/results/"


# ---------------------------------------------------------------------- wording
@pytest.mark.parametrize("page", [*USER_PAGES, README], ids=lambda p: p.name)
def test_user_pages_hold_no_bookkeeping(page):
    found = bookkeeping(page_text(page))
    assert not found, f"{page.name}: {found} (goals, machine load and lost runs belong in docs/results/)"


def test_bookkeeping_is_recognised():
    planted = [
        "the Air3D switch: 60-80 us (goal 50: missed)",
        "The goal is met from 422 s on.",
        "two runs on the quiet 2-core machine",
        "it ran beside a test run",
        "measured beside other work",
        "the machine was busy with training",
        "were lost with their machine",
        "this session used 28 minutes of device time",
    ]
    for line in planted:
        assert bookkeeping(line), f"not recognised: {line!r}"
    clean = (
        "The evader reaches its goal in 82 % of episodes; every goal reached in time.\n"
        "The command ends quietly with status 141. A metric of the run is met by the filter.\n"
        "Results on shared storage stay readable; other processes keep the cores running."
    )
    assert bookkeeping(clean) == []


@pytest.mark.parametrize(
    "page",
    [*USER_PAGES, README, *sorted(RESULTS.glob("*.md")), *sorted((DOCS / "studies").glob("*.md"))],
    ids=lambda p: p.relative_to(ROOT).as_posix(),
)
def test_certify_means_a_proof(page):
    found = [m.group(0) for m in CERTIFIED_STATISTICS.finditer(page_text(page))]
    assert not found, f"{page.name}: {found} (the statistical guarantee is a scenario bound, set or volume)"


def test_certified_statistics_are_recognised():
    for planted in ("certified volume 0.79", "certified vol.", "robust certified volume", "statistical certificate"):
        assert CERTIFIED_STATISTICS.search(planted), planted
    assert not CERTIFIED_STATISTICS.search("a formally certified safe set; robust scenario volume 0.813")


@pytest.mark.parametrize("page", sorted(p for p in RESULTS.glob("*.md") if p.name != "index.md"), ids=lambda p: p.name)
def test_results_pages_state_their_hardware(page):
    assert "**Hardware.**" in page_text(page), f"docs/results/{page.name} does not say what it ran on"


# ---------------------------------------------------------------------- lists checked against the code
def registered_env_ids() -> set[str]:
    import gymnasium as gym

    import reach_envs  # noqa: F401  (registers its environments)

    return {env_id for env_id, spec in gym.registry.items() if str(spec.entry_point).startswith("reach_envs")}


def shipped_models() -> set[str]:
    from training import pretrained

    return set(pretrained.names())


def cli_commands() -> set[str]:
    from reach_cli import COMMANDS, build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    names = {module.__name__.rsplit(".", 1)[1].replace("_", "-") for module in COMMANDS}
    assert names == set(sub.choices), (
        f"reach_cli.COMMANDS {sorted(names)} differ from the parser's {sorted(sub.choices)}"
    )
    return names


def marked(text: str, name: str) -> str:
    """The text between ``<!-- name -->`` and ``<!-- /name -->``; fails when the markers are missing."""
    found = re.findall(rf"<!-- {name} -->(.*?)<!-- /{name} -->", text, flags=re.S)
    assert len(found) == 1, f"expected one <!-- {name} --> ... <!-- /{name} --> list, found {len(found)}"
    return found[0]


def listed(text: str) -> dict[str, list[str]]:
    """The env ids, model names and commands a page lists between its markers (repeats kept)."""
    return {
        "envs": re.findall(r"`([A-Za-z0-9]+-v\d+)`", marked(text, "envs")),
        "models": re.findall(r"`pretrained:([a-z0-9_]+)`", marked(text, "models")),
        "commands": re.findall(r"\breach ([a-z][a-z-]*)", marked(text, "commands")),
    }


def list_problems(text: str, truth: dict[str, set[str]]) -> list[str]:
    """How a page's lists differ from the registry, the shipped models and the CLI."""
    problems = []
    for what, names in listed(text).items():
        missing, extra = truth[what] - set(names), set(names) - truth[what]
        repeated = sorted({n for n in names if names.count(n) > 1})
        problems += [f"{what}: {label} {sorted(s)}" for label, s in (("missing", missing), ("unknown", extra)) if s]
        problems += [f"{what}: listed twice {repeated}"] if repeated else []
    # anywhere on the page, an env id or a pretrained source must exist
    stale_envs = set(re.findall(r"\b([A-Z][A-Za-z0-9]*-v\d+)\b", text)) - truth["envs"]
    stale_models = set(re.findall(r"\bpretrained:([a-z0-9_]+)", text)) - truth["models"]
    problems += [f"envs: no such env {sorted(stale_envs)}"] if stale_envs else []
    problems += [f"models: no such model {sorted(stale_models)}"] if stale_models else []
    return problems


@pytest.fixture(scope="module")
def truth() -> dict[str, set[str]]:
    return {"envs": registered_env_ids(), "models": shipped_models(), "commands": cli_commands()}


@pytest.mark.parametrize("page", [README, DOCS / "index.md"], ids=lambda p: p.name)
def test_the_doors_list_what_ships(page, truth):
    problems = list_problems(page_text(page), truth)
    assert not problems, f"{page.name}: {problems}"


def test_list_problems_are_found(truth):
    envs = ", ".join(f"`{e}`" for e in sorted(truth["envs"] - {"Air3D-v0"}))
    models = ", ".join(f"`pretrained:{m}`" for m in [*sorted(truth["models"]), "air3d"])
    commands = "\n".join(f"reach {c}" for c in [*sorted(truth["commands"]), "fly"])
    page = (
        f"<!-- envs -->{envs}<!-- /envs -->\n<!-- models -->{models}<!-- /models -->\n"
        f"<!-- commands -->\n{commands}\n<!-- /commands -->\nSee Pendulum-v9 and pretrained:nothing."
    )
    problems = " ".join(list_problems(page, truth))
    for expected in ("envs: missing ['Air3D-v0']", "listed twice ['air3d']", "commands: unknown ['fly']",
                     "no such env ['Pendulum-v9']", "no such model ['nothing']"):  # fmt: skip
        assert expected in problems, (expected, problems)
    with pytest.raises(AssertionError, match="envs"):
        listed("no markers here")
