"""Fail when a function of the installed package is too complex or too long (radon's cyclomatic complexity)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from radon.complexity import cc_visit
from radon.visitors import Function

MAX_COMPLEXITY = 20
MAX_LINES = 80
PACKAGE_DIRS = ("sgde_plugin", "adapters", "export")


def offenders(root: Path, allowed: set[str]) -> tuple[list[str], list[str]]:
    """(violations, allow-listed entries that no longer violate) under the package folders of `root`."""
    found: list[str] = []
    seen: set[str] = set()
    for folder in PACKAGE_DIRS:
        for path in sorted((root / folder).rglob("*.py")):
            for block in cc_visit(path.read_text()):
                if not isinstance(block, Function):
                    continue
                name = f"{path.relative_to(root)}:{block.fullname}"
                lines = block.endline - block.lineno + 1
                if block.complexity > MAX_COMPLEXITY or lines > MAX_LINES:
                    seen.add(name)
                    if name not in allowed:
                        found.append(f"{name}: complexity {block.complexity}, {lines} lines")
    return found, sorted(allowed - seen)


def main() -> int:
    """Print every function over the limits that is not allow-listed; exit 1 when there is one."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--root", default=".")
    parser.add_argument("--allow", default="tools/complexity_allow.txt")
    args = parser.parse_args()
    root = Path(args.root)
    allow_file = root / args.allow
    allowed = set()
    if allow_file.exists():
        allowed = {ln.split("#")[0].strip() for ln in allow_file.read_text().splitlines()} - {""}
    found, stale = offenders(root, allowed)
    for line in found:
        print(f"too complex: {line} (limits: complexity {MAX_COMPLEXITY}, {MAX_LINES} lines)")
    for name in stale:
        print(f"note: allow-list entry now within limits, remove it: {name}")
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
