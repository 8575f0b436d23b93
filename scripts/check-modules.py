#!/usr/bin/env python3
"""The Rust crates' module rules: no file-level cycle of `crate::`/`super::` paths, and no source
file over 450 lines, test modules excluded in both.

A cycle means two modules each need the other, so neither can be read, tested or moved alone.
Usage: scripts/check-modules.py [--show]   (--show prints every file's edges and sizes)
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
CRATES = ("server/src", "capture/src", "client/src")
MAX_LINES = 450

TEST_MODULE = re.compile(r"#\[cfg\(test\)\]\s*(?:#\[[^\]]*\]\s*)*(?:pub(?:\([^)]*\))?\s+)?mod\s+(\w+)\s*([;{])")
PATH_START = re.compile(r"\b(crate|super)::")


def strip_comments(text: str) -> str:
    text = re.sub(r"/\*.*?\*/", "", text, flags=re.S)
    return re.sub(r"//[^\n]*", "", text)


def strip_test_modules(text: str) -> tuple[str, list[str]]:
    """The text without inline `#[cfg(test)] mod x { .. }` blocks, and the names of out-of-line ones."""
    out_of_line = []
    while match := TEST_MODULE.search(text):
        if match.group(2) == ";":
            out_of_line.append(match.group(1))
            text = text[: match.start()] + text[match.end() :]
            continue
        depth, end = 0, match.end() - 1
        for end in range(match.end() - 1, len(text)):
            depth += {"{": 1, "}": -1}.get(text[end], 0)
            if depth == 0:
                break
        text = text[: match.start()] + text[end + 1 :]
    return text, out_of_line


def module_of(root: Path, file: Path) -> list[str]:
    parts = list(file.relative_to(root).with_suffix("").parts)
    if parts[-1] in ("mod", "lib", "main"):
        parts.pop()
    return parts


def expand(path: str) -> list[str]:
    """`a::{b, c::{d, e}}` -> [`a::b`, `a::c::d`, `a::c::e`]."""
    brace = path.find("{")
    if brace < 0:
        return [path.strip()]
    prefix, inner = path[:brace], path[brace + 1 : path.rfind("}")]
    items, depth, start = [], 0, 0
    for index, char in enumerate(inner):
        depth += {"{": 1, "}": -1}.get(char, 0)
        if char == "," and depth == 0:
            items.append(inner[start:index])
            start = index + 1
    items.append(inner[start:])
    return [expanded for item in items if item.strip() for expanded in expand(prefix + item.strip())]


def paths_in(text: str) -> list[str]:
    """Every `crate::..`/`super::..` path, braces expanded."""
    found = []
    for match in PATH_START.finditer(text):
        index, depth = match.end(), 0
        while index < len(text):
            char = text[index]
            if char == "{":
                depth += 1
            elif char == "}":
                if depth == 0:
                    break
                depth -= 1
            elif depth == 0 and not (char.isalnum() or char in "_:"):
                break
            index += 1
        found.extend(expand(text[match.start() : index]))
    return found


def resolve(path: str, here: list[str], modules: dict[tuple, Path]) -> Path | None:
    parts = [part.strip() for part in path.split("::") if part.strip()]
    base: list[str] = []
    if parts[0] == "crate":
        parts = parts[1:]
    else:
        base = list(here)
        while parts and parts[0] == "super":
            base.pop()
            parts = parts[1:]
    if parts and parts[0] == "self":
        parts = parts[1:]
    full = base + parts
    for length in range(len(full), -1, -1):
        if tuple(full[:length]) in modules:
            return modules[tuple(full[:length])]
    return None


def crate_graph(root: Path) -> tuple[dict[Path, set[Path]], dict[Path, int]]:
    files = sorted(root.rglob("*.rs"))
    texts, tests = {}, set()
    for file in files:
        text, out_of_line = strip_test_modules(strip_comments(file.read_text()))
        texts[file] = text
        directory = file.parent if file.stem in ("mod", "lib", "main") else file.with_suffix("")
        tests.update(directory / f"{name}.rs" for name in out_of_line)
        tests.update(directory / name / "mod.rs" for name in out_of_line)
    modules = {tuple(module_of(root, file)): file for file in files if file not in tests}
    graph: dict[Path, set[Path]] = {}
    for here, file in modules.items():
        edges = {resolve(path, list(here), modules) for path in paths_in(texts[file])}
        graph[file] = {edge for edge in edges if edge is not None and edge != file}
    return graph, {file: texts[file].count("\n") for file in modules.values()}


def cycles(graph: dict[Path, set[Path]]) -> list[list[Path]]:
    """Strongly connected components with more than one file (Tarjan)."""
    index: dict[Path, int] = {}
    low: dict[Path, int] = {}
    stack: list[Path] = []
    found = []

    def visit(node: Path) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for edge in graph.get(node, ()):
            if edge not in index:
                visit(edge)
                low[node] = min(low[node], low[edge])
            elif edge in stack:
                low[node] = min(low[node], index[edge])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    sys.setrecursionlimit(10_000)
    for node in graph:
        if node not in index:
            visit(node)
    return found


def main() -> int:
    failures = []
    for crate in CRATES:
        root = REPO / crate
        graph, sizes = crate_graph(root)
        if "--show" in sys.argv:
            for file, edges in sorted(graph.items()):
                names = ", ".join(str(edge.relative_to(root)) for edge in sorted(edges))
                print(f"{file.relative_to(REPO)} ({sizes[file]} lines) -> {names}")
        for component in cycles(graph):
            names = ", ".join(str(file.relative_to(root)) for file in component)
            failures.append(f"{crate}: cycle of {len(component)} files: {names}")
        for file, lines in sorted(sizes.items()):
            if lines > MAX_LINES:
                failures.append(f"{file.relative_to(REPO)}: {lines} lines without its tests (limit {MAX_LINES})")
    for failure in failures:
        print(failure, file=sys.stderr)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
