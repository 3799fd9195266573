"""A small reader of the Dockerfile and .dockerignore, for checks that need no container engine.

It knows the subset of the Dockerfile syntax this repository uses (FROM, ENV, WORKDIR, COPY,
RUN, USER, EXPOSE, HEALTHCHECK, CMD, ARG, LABEL) and refuses anything else, so a new kind of
instruction makes the deploy tests fail loudly instead of being skipped in silence.
"""

from __future__ import annotations

import json
import os
import re
import shlex
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
DOCKERFILE = REPO / "Dockerfile"
DOCKERIGNORE = REPO / ".dockerignore"

KNOWN = {"FROM", "ENV", "WORKDIR", "COPY", "RUN", "USER", "EXPOSE", "HEALTHCHECK", "CMD", "ARG", "LABEL"}


@dataclass
class Instruction:
    """One Dockerfile instruction: its keyword, its ``--flag=value`` options and the rest."""

    keyword: str
    flags: dict[str, str]
    args: str
    line: int


@dataclass
class Stage:
    """One ``FROM ... AS name`` stage and its instructions."""

    base: str
    name: str
    instructions: list[Instruction] = field(default_factory=list)

    def of(self, keyword: str) -> list[Instruction]:
        return [i for i in self.instructions if i.keyword == keyword]


def _logical_lines(text: str) -> Iterator[tuple[int, str]]:
    """Join backslash continuations; drop comments and blank lines (as Docker's parser does)."""
    buf: list[str] = []
    start = 0
    for number, raw in enumerate(text.splitlines(), start=1):
        stripped = raw.strip()
        if stripped.startswith("#") or (not stripped and not buf):
            continue
        if not buf:
            start = number
        if stripped.endswith("\\"):
            buf.append(stripped[:-1].strip())
            continue
        buf.append(stripped)
        yield start, " ".join(part for part in buf if part)
        buf = []
    if buf:
        raise ValueError(f"Dockerfile ends inside a continued line that starts at line {start}")


def _split_flags(rest: str) -> tuple[dict[str, str], str]:
    flags: dict[str, str] = {}
    while rest.startswith("--"):
        token, _, rest = rest.partition(" ")
        name, _, value = token[2:].partition("=")
        flags[name] = value
        rest = rest.lstrip()
    return flags, rest


def parse_dockerfile(path: Path = DOCKERFILE) -> list[Stage]:
    """The stages of ``path``, each with its instructions in order."""
    stages: list[Stage] = []
    for line, text in _logical_lines(path.read_text()):
        keyword, _, rest = text.partition(" ")
        keyword = keyword.upper()
        if keyword not in KNOWN:
            raise ValueError(f"{path}:{line}: instruction {keyword} is not understood by tests/deploy")
        flags, rest = _split_flags(rest.strip())
        ins = Instruction(keyword, flags, rest, line)
        if keyword == "FROM":
            words = rest.split()
            name = words[2] if len(words) == 3 and words[1].upper() == "AS" else str(len(stages))
            stages.append(Stage(base=words[0], name=name))
        elif not stages:
            if keyword != "ARG":
                raise ValueError(f"{path}:{line}: {keyword} before the first FROM")
        else:
            stages[-1].instructions.append(ins)
    return stages


def env_pairs(args: str) -> list[tuple[str, str]]:
    """``ENV a=1 b="x y"`` as [(a, 1), (b, x y)]; the legacy ``ENV a 1`` form too."""
    words = shlex.split(args)
    if words and "=" not in words[0]:
        return [(words[0], " ".join(words[1:]))]
    return [tuple(w.split("=", 1)) for w in words]  # type: ignore[misc]


def exec_form(args: str) -> list[str]:
    """The JSON array of a CMD or HEALTHCHECK CMD; shell form is refused (no signals to PID 1)."""
    if args.startswith("CMD "):
        args = args[4:]
    value = json.loads(args)
    if not (isinstance(value, list) and all(isinstance(v, str) for v in value)):
        raise ValueError(f"expected a JSON array of strings, found {args!r}")
    return value


def expand(value: str, env: dict[str, str]) -> str:
    """Substitute ``$VAR`` and ``${VAR}`` from ``env`` (unknown variables become empty, as in Docker)."""
    return re.sub(r"\$\{(\w+)\}|\$(\w+)", lambda m: env.get(m.group(1) or m.group(2), ""), value)


# --- .dockerignore --------------------------------------------------------------------------

def read_dockerignore(path: Path = DOCKERIGNORE) -> list[str]:
    patterns = []
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if line and not line.startswith("#"):
            patterns.append(line)
    return patterns


def _pattern_regex(pattern: str) -> re.Pattern[str]:
    """Docker's pattern syntax (Go's filepath.Match plus ``**``) as an anchored regex."""
    out = []
    i = 0
    while i < len(pattern):
        c = pattern[i]
        if pattern.startswith("**/", i):
            out.append("(?:.*/)?")
            i += 3
            continue
        if pattern.startswith("**", i):
            out.append(".*")
            i += 2
            continue
        out.append("[^/]*" if c == "*" else "[^/]" if c == "?" else re.escape(c))
        i += 1
    return re.compile("".join(out) + r"\Z")


def _clean(pattern: str) -> str:
    return os.path.normpath(pattern).lstrip("/")


class DockerIgnore:
    """Which paths of the build context reach the builder, by Docker's rules: the last matching
    pattern wins, ``!`` re-includes, and a pattern that matches a parent folder matches its files."""

    def __init__(self, patterns: list[str]) -> None:
        self.rules = []
        for p in patterns:
            negate = p.startswith("!")
            cleaned = _clean(p[1:] if negate else p)
            self.rules.append((negate, cleaned, _pattern_regex(cleaned)))

    def excluded(self, rel: str) -> bool:
        rel = _clean(rel)
        parts = rel.split("/")
        candidates = ["/".join(parts[: k + 1]) for k in range(len(parts))]
        result = False
        for negate, _, regex in self.rules:
            if any(regex.match(c) for c in candidates):
                result = not negate
        return result

    def may_reinclude_under(self, rel_dir: str) -> bool:
        """Whether some ``!`` pattern could let a file below the excluded folder ``rel_dir`` back in."""
        for negate, cleaned, _ in self.rules:
            if negate and (cleaned == rel_dir or cleaned.startswith(rel_dir + "/") or cleaned[0] in "*?["):
                return True
        return False

    def context_files(self, root: Path = REPO) -> list[str]:
        """Every file of the build context rooted at ``root``, as relative POSIX paths."""
        found = []
        for dirpath, dirnames, filenames in os.walk(root):
            rel_dir = Path(dirpath).relative_to(root).as_posix()
            keep = []
            for d in dirnames:
                rel = d if rel_dir == "." else f"{rel_dir}/{d}"
                if d == ".git" or (self.excluded(rel) and not self.may_reinclude_under(rel)):
                    continue
                keep.append(d)
            dirnames[:] = sorted(keep)
            for f in filenames:
                rel = f if rel_dir == "." else f"{rel_dir}/{f}"
                if not self.excluded(rel):
                    found.append(rel)
        return sorted(found)
