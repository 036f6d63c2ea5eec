"""Writes docs/cli.md from `python -m ccp_jax.train --help`, at a fixed width so the page does not depend on the
terminal that made it. tests/test_config.py fails when the page is stale.

    python docs/make_cli.py           # rewrite docs/cli.md
    python docs/make_cli.py --check   # exit 1 if docs/cli.md is not what --help says
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PAGE = ROOT / "docs" / "cli.md"
COLUMNS = 100

HEADER = """# Command line

Every flag of `python -m ccp_jax.train` (console script `ccp-train`), as `--help` prints it. The defaults shown
are the `small` preset's, the CLI's default; `--preset` (and `--resume`) change them, and `--help` given with
them shows theirs. Each setting is declared once, with this text, in `ccp_jax/config.py`
([design.md](design.md#configuration)). Regenerate this page with `python docs/make_cli.py`.

```
"""


def help_text() -> str:
    """`--help` at `COLUMNS` columns, without colours."""
    env = {**os.environ, "COLUMNS": str(COLUMNS), "TERM": "dumb", "NO_COLOR": "1",
           "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    env.pop("FORCE_COLOR", None)
    done = subprocess.run([sys.executable, "-m", "ccp_jax.train", "--help"], cwd=ROOT, env=env, capture_output=True,
                          text=True, check=True)
    return "\n".join(line.rstrip() for line in done.stdout.splitlines())


def page() -> str:
    return HEADER + help_text() + "\n```\n"


def main(argv: list[str]) -> int:
    text = page()
    if "--check" in argv:
        if not PAGE.exists() or PAGE.read_text() != text:
            print(f"{PAGE} is stale: run python docs/make_cli.py", file=sys.stderr)
            return 1
        return 0
    PAGE.write_text(text)
    print(f"wrote {PAGE}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
