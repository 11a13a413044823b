"""Put the output of `make demo-queries` (the three demo queries `make run` prints) into the README, between
its demo markers, so the demo the README shows is the words of a real run, never typed by hand.

    python -m tools.demo_doc                   # runs `make -s demo-queries`, rewrites README.md's demo block
    python -m tools.demo_doc --from run.txt    # the same from a saved output (of make run or demo-queries)

The first query's JSON answer (less the CLI's ``exif_check``) also becomes docs/api.md's example answer,
between its ``demo-answer`` markers: the fields explained there are those of the same run.

Run it after `make run` (or `make demo`): the queries need the fitted pipeline and the demo collection.
`make demo-doc` runs the first form. GEOLOC_DATA_DIR points the queries at another data dir.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
API_DOC = REPO / "docs" / "api.md"
BEGIN, END = "<!-- demo:start -->", "<!-- demo:end -->"
ANSWER_BEGIN, ANSWER_END = "<!-- demo-answer:start -->", "<!-- demo-answer:end -->"
#: The first line `make demo-queries` prints, and the line `make run` prints after the last query.
FIRST = "--- demo query 1"
AFTER = "--- the geoloc command is in .venv"


def demo_output(text: str) -> str:
    """The demo queries' lines of ``text`` (a `make run` transcript or `make demo-queries`'s output)."""
    if FIRST not in text:
        raise SystemExit(f"no demo query in the output (no line starting {FIRST!r})")
    text = text[text.index(FIRST) :]
    if AFTER in text:
        text = text[: text.index(AFTER)]
    return text.strip() + "\n"


def block(output: str) -> str:
    """The README's block: the markers around a fenced transcript (``text``, so no test runs it as a command)."""
    return f"{BEGIN}\n```text\n$ make demo-queries\n{output}```\n{END}"


def replace_between(text: str, begin: str, end: str, inner: str) -> str:
    pattern = re.compile(re.escape(begin) + r".*?" + re.escape(end), re.S)
    if not pattern.search(text):
        raise SystemExit(f"no {begin} ... {end} block to replace")
    return pattern.sub(lambda _: f"{begin}\n{inner}\n{end}", text, count=1)


def replace_block(readme: str, output: str) -> str:
    return replace_between(readme, BEGIN, END, block(output)[len(BEGIN) + 1 : -len(END) - 1])


def first_answer(output: str) -> dict:
    """The first query's JSON answer, as /locate gives it (the CLI's ``exif_check`` left out)."""
    start = output.index("\n{") + 1
    answer, _ = json.JSONDecoder().raw_decode(output[start:])
    answer.pop("exif_check", None)
    return answer


def answer_block(answer: dict) -> str:
    """The answer in a ``json`` fence, one candidate per line, so the page stays short and readable."""
    lines = ["{", ' "candidates": [']
    cands = answer["candidates"]
    lines += [f"  {json.dumps(c)}" + ("," if i < len(cands) - 1 else "") for i, c in enumerate(cands)]
    lines.append(" ],")
    rest = [k for k in answer if k != "candidates"]
    lines += [
        f" {json.dumps(k)}: {json.dumps(answer[k])}" + ("," if i < len(rest) - 1 else "") for i, k in enumerate(rest)
    ]
    lines.append("}")
    return "```json\n" + "\n".join(lines) + "\n```"


def run_queries() -> str:
    """The queries' output as a terminal shows it: stderr (the EXIF comparison) in place, unbuffered."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    p = subprocess.run(
        ["make", "-s", "--no-print-directory", "demo-queries"],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    if p.returncode != 0:
        raise SystemExit(f"make demo-queries failed (exit {p.returncode}):\n{p.stdout[-2000:]}")
    return p.stdout


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--from", dest="source", type=Path, help="a saved output instead of running the queries")
    ap.add_argument("--readme", type=Path, default=README)
    ap.add_argument("--api-doc", type=Path, default=API_DOC)
    args = ap.parse_args(argv)
    output = demo_output(args.source.read_text() if args.source else run_queries())
    args.readme.write_text(replace_block(args.readme.read_text(), output))
    first = first_answer(output)
    if first["estimate"] is None:  # the API page's example explains an estimate's fields: it needs one
        print(f"wrote the demo block of {args.readme}; the first answer states no estimate: {args.api_doc} kept")
        return 0
    answer = answer_block(first)
    args.api_doc.write_text(replace_between(args.api_doc.read_text(), ANSWER_BEGIN, ANSWER_END, answer))
    print(f"wrote the demo block of {args.readme} ({len(output.splitlines())} lines) and the answer in {args.api_doc}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
