"""The code's own measures (issue 27): the longest functions, the largest modules and the Solver's
size, from the source (``ast``; the generated dcrad/v1 left out).  No assertions.

Run: .venv/bin/python bench/bench_code.py [root]   (default: this checkout)
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path


def main() -> int:
    root = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parents[1]
    functions, modules = [], []
    files = [*root.glob("dcrad/**/*.py"), *root.glob("coordinator/*.py"), *root.glob("worker/*.py")]
    for path in files:
        if "v1" in path.relative_to(root).parts:
            continue
        src = path.read_text()
        rel = path.relative_to(root).as_posix()
        modules.append((len(src.splitlines()), rel))
        for node in ast.walk(ast.parse(src)):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                functions.append((node.end_lineno - node.lineno + 1, f"{rel}:{node.name}"))
            if isinstance(node, ast.ClassDef) and node.name == "Solver":
                methods = sum(isinstance(b, ast.FunctionDef) for b in node.body)
                print(f"Solver: {node.end_lineno - node.lineno + 1} lines, {methods} methods")
    print("longest functions:", ", ".join(f"{name} {n}" for n, name in sorted(functions, reverse=True)[:5]))
    print("largest modules:", ", ".join(f"{name} {n}" for n, name in sorted(modules, reverse=True)[:4]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
