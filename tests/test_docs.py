"""The documentation stays short, true to the tree and true to the code: the README's size, every repository
path the pages name, the generated configuration page, the demo block written from a real run, and every
endpoint of the served OpenAPI document on the API page."""

from __future__ import annotations

import json
import re
import subprocess

import pytest

from tests.conftest import REPO
from tools import config_docs, demo_doc

PAGES = [REPO / "README.md", REPO / "CHANGELOG.md", *sorted((REPO / "docs").glob("*.md"))]
#: Where a repository path starts; anything else in backticks is a value, a command or a placeholder.
ROOTS = ("app/", "bench/", "tests/", "docs/", "tools/", "models/", "index/", "data/", "web/")
FENCE = re.compile(r"^```.*?^```", re.S | re.M)
LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")


def test_the_readme_is_read_in_five_minutes():
    assert len((REPO / "README.md").read_bytes()) <= 15_000


@pytest.mark.parametrize("name", ["results.md", "benchmarks.md"])
def test_results_and_benchmarks_keep_the_current_figures_only(name):
    page = (REPO / "docs" / name).read_text()
    assert len(page.encode()) <= 30_000, name
    assert "git show 965af43:docs/" in page, "the page says where its history is"


def repo_paths(text: str) -> set[str]:
    """The repository paths a page names: link targets, and single-token code spans (outside fenced blocks)
    that start at a top-level folder of ours, or hold a slash and end in a source or document suffix."""
    prose = FENCE.sub("", text)
    found = {t for t in LINK.findall(prose) if not re.match(r"[a-z]+://", t)}
    for span in re.findall(r"`([^`\s]+)`", prose):
        span = span.rstrip(".,:;)").split("::")[0]  # a pytest node id names its file
        if re.search(r"[*{}<>$]|\.\.\.|[A-Z]{2,}", span):  # a pattern or a placeholder (CONFIG, SHA256, ...)
            continue
        if span.startswith(ROOTS) or ("/" in span and re.search(r"\.(py|md|toml|yml|yaml)$", span)):
            found.add(span)
    return found


def _ignored(path: str) -> bool:
    """A build output the set-up makes (models/, index/, data/, the vendored web files): git ignores it."""
    return subprocess.run(["git", "check-ignore", "-q", path], cwd=REPO).returncode == 0


def test_every_path_the_docs_name_exists():
    missing = []
    for page in PAGES:
        for path in sorted(repo_paths(page.read_text())):
            target = (page.parent / path) if page.parent != REPO and not path.startswith(ROOTS) else REPO / path
            if not target.exists() and not _ignored(str(target.relative_to(REPO))):
                missing.append(f"{page.relative_to(REPO)}: {path}")
    assert missing == []


def test_the_path_finder_finds_paths_and_skips_the_rest():
    text = "see `app/cli.py`, `docs/nope.md` and [x](guide.md), not `--data-dir D`, `index/*.faiss`"
    text += "\n```\n`app/x.py`\n```"
    assert repo_paths(text) == {"app/cli.py", "docs/nope.md", "guide.md"}


def test_the_configuration_page_matches_settings(tmp_path):
    assert config_docs.main(["--check"]) == 0, "run: python -m tools.config_docs"
    page = (REPO / "docs" / "configuration.md").read_text()
    from app.settings import Settings

    for name in Settings.model_fields:
        assert f"`GEOLOC_{name.upper()}`" in page, name
    stale = tmp_path / "configuration.md"
    stale.write_text(page.replace("GEOLOC_DATA_DIR", "GEOLOC_DATA_FOLDER"))
    assert config_docs.main(["--check", "--out", str(stale)]) == 1


def _demo_block(readme: str) -> str:
    assert readme.count(demo_doc.BEGIN) == 1 and readme.count(demo_doc.END) == 1
    assert readme.index(demo_doc.BEGIN) < readme.index(demo_doc.END)
    return readme[readme.index(demo_doc.BEGIN) : readme.index(demo_doc.END) + len(demo_doc.END)]


def test_the_readme_demo_block_is_a_run_of_the_three_queries():
    """The block is what tools/demo_doc.py writes from `make demo-queries`: the three queries' headers in
    order, the first one's JSON answer, and the block rewritten from its own text is the same block.
    docs/api.md's example answer is a run of the same query too (``make demo-doc`` writes both), but one
    that states an estimate, so it can explain an estimate's fields (test_readme_commands checks them
    against a real server's answer): it stays as written while the demo's own run states none."""
    readme = (REPO / "README.md").read_text()
    block = _demo_block(readme)
    assert block.startswith(f"{demo_doc.BEGIN}\n```text\n$ make demo-queries\n") and block.endswith(
        f"```\n{demo_doc.END}"
    )
    heads = [line for line in block.splitlines() if line.startswith("--- demo query")]
    assert [h.split(",")[0] for h in heads] == ["--- demo query 1", "--- demo query 2", "--- demo query 3"]
    output = demo_doc.demo_output(block.split("$ make demo-queries\n", 1)[1].rsplit("```", 1)[0])
    answer = demo_doc.first_answer(output)
    assert answer["candidates"] and "estimate" in answer and "reason_code" in answer
    assert demo_doc.replace_block(readme, output) == readme
    api = (REPO / "docs" / "api.md").read_text()
    example = api.split(demo_doc.ANSWER_BEGIN, 1)[1].split(demo_doc.ANSWER_END, 1)[0]
    shown = json.loads(re.search(r"```json\n(.*?)```", example, re.S).group(1))
    assert shown["estimate"] is not None and shown["candidates"][0]["label"] == answer["candidates"][0]["label"]


def test_demo_doc_keeps_the_api_example_when_the_demo_states_no_estimate(tmp_path):
    """`make demo-doc` from a saved run (the README's own block): the README's block is rewritten from it; the
    API page's example is replaced only by an answer that states an estimate, else kept as it was."""
    readme = (REPO / "README.md").read_text()
    block = _demo_block(readme)
    saved = tmp_path / "run.txt"
    saved.write_text(block.split("$ make demo-queries\n", 1)[1].rsplit("```", 1)[0])
    first = demo_doc.first_answer(demo_doc.demo_output(saved.read_text()))
    (tmp_path / "README.md").write_text(readme.replace(block, f"{demo_doc.BEGIN}\nold\n{demo_doc.END}"))
    api = (REPO / "docs" / "api.md").read_text()
    (tmp_path / "api.md").write_text(api)
    args = ["--from", str(saved), "--readme", str(tmp_path / "README.md"), "--api-doc", str(tmp_path / "api.md")]
    assert demo_doc.main(args) == 0
    assert (tmp_path / "README.md").read_text() == readme
    written = (tmp_path / "api.md").read_text()
    if first["estimate"] is None:
        assert written == api
    else:
        assert demo_doc.answer_block(first) in written


def test_make_demo_queries_are_the_lines_make_run_prints():
    def dry(target: str) -> list[str]:
        p = subprocess.run(["make", "-n", "-B", target], capture_output=True, text=True, cwd=REPO)
        assert p.returncode == 0, p.stderr
        return [line for line in p.stdout.splitlines() if "demo query" in line or " locate " in line]

    queries = dry("demo-queries")
    assert len([q for q in queries if " locate " in q]) == 3
    assert queries == dry("run")
    assert (
        "tools.demo_doc" in subprocess.run(["make", "-n", "demo-doc"], capture_output=True, text=True, cwd=REPO).stdout
    )


def test_the_api_page_names_every_endpoint_of_the_openapi_document(tmp_path):
    from app.api.app import create_app
    from app.settings import Settings

    spec = create_app(Settings(data_dir=tmp_path / "data", no_auth=True)).openapi()
    api = (REPO / "docs" / "api.md").read_text()
    missing = [f"{m.upper()} {p}" for p, ops in spec["paths"].items() for m in ops if f"`{m.upper()} {p}`" not in api]
    assert missing == [] and len(spec["paths"]) >= 10
