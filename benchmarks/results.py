"""One schema for every benchmark's result: what ran, where, when, at which commit, and its numbers.

Each benchmark writes ``benchmarks/results/<benchmark>.json`` through :func:`write_result`, which
fills in the machine, the date and the commit itself; ``python benchmarks/render.py`` builds
``docs/benchmarks.md`` from these files.  A file holds one measurement, the current one: a rerun
replaces it (the history is git's).  Raw outputs (every run, every draw) go beside them, under
``benchmarks/results/raw/``, and a result names them in ``data``.

The file, as :meth:`Result.to_dict` writes it::

    {"schema": 1,
     "benchmark": "twin",                     # the file's name without .json
     "title": "Twin (RAYX)",                  # the page's heading (its anchor: render.slug)
     "command": "python benchmarks/bench_twin.py",
     "machine": {"description": "AMD EPYC, 2 cores, Python 3.11.7", "cores": 2, ...},
     "date": "2026-11-21",                    # or null: not recorded
     "commit": "955cff9",                     # or a list of commits, or null: not recorded
     "summary": "One paragraph: what is measured and how to read it.",
     "tables": [{"caption": "...", "columns": ["rays", "s"], "rows": [["10,000", 0.15]],
                 "align": ["r", "r"]}],        # align optional: "l" or "r" per column
     "notes": ["..."],
     "data": ["benchmarks/results/raw/twin.json"],   # raw outputs, paths from the repository root
     "figures": [{"path": "docs/img/x.png", "caption": "..."}],
     "source": null}                          # where the numbers came from, if not from a run
"""

from __future__ import annotations

import datetime
import json
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Union

SCHEMA = 1
HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
RESULTS = HERE / "results"
RAW = RESULTS / "raw"

Cell = Union[str, int, float, bool, None]
_ID = re.compile(r"^[a-z0-9][a-z0-9_.-]*$")
_COMMIT = re.compile(r"^[0-9a-f]{7,40}$")
_KEYS = ("schema", "benchmark", "title", "command", "machine", "date", "commit", "summary", "tables", "notes",
         "data", "figures", "source")
_REQUIRED = ("schema", "benchmark", "title", "command", "machine", "date", "commit", "summary")


@dataclass(frozen=True)
class Table:
    """A table of a result: its caption, column headings, rows of cells, and optional alignment.

    Parameters
    ----------
    caption : str
        One line above the table: what its rows are.
    columns : sequence of str
        The column headings.
    rows : sequence of sequences
        Each row's cells (str, int, float, bool or None), as many as there are columns.
    align : sequence of {"l", "r"}, optional
        Per column; by default numbers right, text left.
    """

    caption: str
    columns: tuple[str, ...]
    rows: tuple[tuple[Cell, ...], ...]
    align: tuple[str, ...] | None = None

    def __post_init__(self):
        # tuples: a frozen result should not change through a list it was given
        object.__setattr__(self, "columns", tuple(self.columns))
        object.__setattr__(self, "rows", tuple(tuple(r) for r in self.rows))
        if self.align is not None:
            object.__setattr__(self, "align", tuple(self.align))

    def to_dict(self) -> dict:
        d = {"caption": self.caption, "columns": list(self.columns), "rows": [list(r) for r in self.rows]}
        if self.align is not None:
            d["align"] = list(self.align)
        return d


@dataclass(frozen=True)
class Figure:
    """An image beside a result: its path from the repository root and a caption."""

    path: str
    caption: str

    def to_dict(self) -> dict:
        return {"path": self.path, "caption": self.caption}


@dataclass(frozen=True)
class Result:
    """One benchmark's current measurement (the module's docstring gives the file's fields)."""

    benchmark: str
    title: str
    command: str
    machine: dict
    date: str | None
    commit: str | tuple[str, ...] | None
    summary: str
    tables: tuple[Table, ...] = ()
    notes: tuple[str, ...] = ()
    data: tuple[str, ...] = ()
    figures: tuple[Figure, ...] = ()
    source: str | None = None

    def __post_init__(self):
        for name in ("tables", "notes", "data", "figures"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        if isinstance(self.commit, list):
            object.__setattr__(self, "commit", tuple(self.commit))
        errors = validate(self.to_dict())
        if errors:
            raise ValueError(f"result {self.benchmark!r}: " + "; ".join(errors))

    def to_dict(self) -> dict:
        """The file's content, keys in the schema's order."""
        return {"schema": SCHEMA, "benchmark": self.benchmark, "title": self.title, "command": self.command,
                "machine": dict(self.machine), "date": self.date,
                "commit": list(self.commit) if isinstance(self.commit, tuple) else self.commit,
                "summary": self.summary, "tables": [t.to_dict() for t in self.tables], "notes": list(self.notes),
                "data": list(self.data), "figures": [f.to_dict() for f in self.figures], "source": self.source}

    @classmethod
    def from_dict(cls, d: dict) -> "Result":
        """A result from a file's content; ValueError names what does not fit the schema."""
        errors = validate(d)
        if errors:
            raise ValueError(f"result {d.get('benchmark')!r}: " + "; ".join(errors))
        return cls(benchmark=d["benchmark"], title=d["title"], command=d["command"], machine=d["machine"],
                   date=d["date"], commit=d["commit"], summary=d["summary"],
                   tables=[Table(**t) for t in d.get("tables", [])], notes=d.get("notes", []),
                   data=d.get("data", []), figures=[Figure(**f) for f in d.get("figures", [])],
                   source=d.get("source"))


def _text(errors: list, name: str, value: Any, one_line: bool = False) -> None:
    if not isinstance(value, str) or not value.strip():
        errors.append(f"{name}: a non-empty string")
    elif one_line and "\n" in value:
        errors.append(f"{name}: one line")


def _check_machine(errors: list, m: Any) -> None:
    if not isinstance(m, dict):
        errors.append("machine: an object")
        return
    _text(errors, "machine.description", m.get("description"), one_line=True)
    for k, v in m.items():
        if not isinstance(v, (str, int)) or isinstance(v, bool):
            errors.append(f"machine.{k}: a string or an integer")


def _check_date(errors: list, date: Any) -> None:
    if date is None:
        return
    try:
        ok = isinstance(date, str) and datetime.date.fromisoformat(date).isoformat() == date
    except ValueError:
        ok = False
    if not ok:
        errors.append(f"date: YYYY-MM-DD or null, not {date!r}")


def _check_commit(errors: list, commit: Any) -> None:
    commits = commit if isinstance(commit, (list, tuple)) else [commit]
    if commit is None:
        return
    if not commits or not all(isinstance(c, str) and _COMMIT.match(c) for c in commits):
        errors.append(f"commit: a hexadecimal commit, a list of them, or null, not {commit!r}")


def _check_table(errors: list, i: int, t: Any) -> None:
    name = f"tables[{i}]"
    if not isinstance(t, dict) or set(t) - {"caption", "columns", "rows", "align"}:
        errors.append(f"{name}: an object with caption, columns, rows and optional align")
        return
    _text(errors, f"{name}.caption", t.get("caption"), one_line=True)
    cols = t.get("columns")
    if not isinstance(cols, (list, tuple)) or not cols or not all(isinstance(c, str) for c in cols):
        errors.append(f"{name}.columns: a non-empty list of strings")
        return
    rows = t.get("rows")
    if not isinstance(rows, (list, tuple)):
        errors.append(f"{name}.rows: a list of rows")
        return
    for j, row in enumerate(rows):
        if not isinstance(row, (list, tuple)) or len(row) != len(cols):
            errors.append(f"{name}.rows[{j}]: {len(cols)} cells")
        elif not all(c is None or isinstance(c, (str, int, float)) for c in row):
            errors.append(f"{name}.rows[{j}]: cells are strings, numbers or null")
        elif any(isinstance(c, str) and "\n" in c for c in row):
            errors.append(f"{name}.rows[{j}]: a cell holds one line")
    align = t.get("align")
    if align is not None and (not isinstance(align, (list, tuple)) or len(align) != len(cols)
                              or not set(align) <= {"l", "r"}):
        errors.append(f"{name}.align: 'l' or 'r' for each column")


def validate(d: Any) -> list[str]:
    """What in ``d`` does not fit the schema (an empty list: it fits).

    Parameters
    ----------
    d : dict
        A result file's content.

    Returns
    -------
    list of str
        One message per problem.
    """
    if not isinstance(d, dict):
        return ["a result is a JSON object"]
    errors = [f"{k}: missing" for k in _REQUIRED if k not in d]
    errors += [f"{k}: not a field of the schema" for k in d if k not in _KEYS]
    if errors:
        return errors
    if d["schema"] != SCHEMA:
        errors.append(f"schema: {SCHEMA}")
    if not isinstance(d["benchmark"], str) or not _ID.match(d["benchmark"]):
        errors.append("benchmark: lower-case letters, digits, '_', '.', '-'")
    _text(errors, "title", d["title"], one_line=True)
    _text(errors, "command", d["command"], one_line=True)
    _text(errors, "summary", d["summary"])
    _check_machine(errors, d["machine"])
    _check_date(errors, d["date"])
    _check_commit(errors, d["commit"])
    for i, t in enumerate(d.get("tables", [])):
        _check_table(errors, i, t)
    for k in ("notes", "data"):
        v = d.get(k, [])
        if not isinstance(v, (list, tuple)) or not all(isinstance(x, str) and x.strip() for x in v):
            errors.append(f"{k}: a list of non-empty strings")
    for i, f in enumerate(d.get("figures", [])):
        if not isinstance(f, dict) or set(f) != {"path", "caption"}:
            errors.append(f"figures[{i}]: an object with path and caption")
    if d.get("source") is not None:
        _text(errors, "source", d["source"], one_line=True)
    return errors


def _dumps(o: Any, indent: int = 0) -> str:
    """JSON with one line per row and per short list: a rerun's diff shows the cells that moved."""
    pad = " " * (indent + 1)
    if isinstance(o, dict) and o:
        items = [f"{pad}{json.dumps(k)}: {_dumps(v, indent + 1)}" for k, v in o.items()]
        return "{\n" + ",\n".join(items) + "\n" + " " * indent + "}"
    if isinstance(o, (list, tuple)) and o:
        flat = all(not isinstance(v, (dict, list, tuple)) for v in o)
        if flat and not any(isinstance(v, str) and len(v) > 100 for v in o):
            return json.dumps(list(o), ensure_ascii=False)
        items = [pad + _dumps(v, indent + 1) for v in o]
        return "[\n" + ",\n".join(items) + "\n" + " " * indent + "]"
    return json.dumps(o, ensure_ascii=False)


def save(result: Result, directory: Path = RESULTS) -> Path:
    """Write ``result`` to ``directory/<benchmark>.json``; return the path."""
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"{result.benchmark}.json"
    path.write_text(_dumps(result.to_dict()) + "\n", encoding="utf-8")
    return path


def load(path: Path) -> Result:
    """The result in ``path``; ValueError when it does not fit the schema or its file's name."""
    d = json.loads(Path(path).read_text(encoding="utf-8"))
    result = Result.from_dict(d)
    if result.benchmark != Path(path).stem:
        raise ValueError(f"{path}: benchmark {result.benchmark!r} is not the file's name")
    return result


def load_all(directory: Path = RESULTS) -> list[Result]:
    """Every result in ``directory`` (not its ``raw/``), by file name."""
    return [load(p) for p in sorted(directory.glob("*.json"))]


def _git(*args: str) -> str | None:
    try:
        r = subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return None
    return r.stdout.strip() if r.returncode == 0 else None


def current_commit() -> tuple[str | None, bool]:
    """The checked-out commit (short hash, or None outside git) and whether tracked files differ from it.

    The results folder does not count: a benchmark writes its raw record there before its result.
    """
    commit = _git("rev-parse", "--short", "HEAD")
    dirty = bool(_git("status", "--porcelain", "--untracked-files=no", "--", ".",
                      f":(exclude){RESULTS.relative_to(ROOT).as_posix()}"))
    return commit, dirty


def invocation() -> str:
    """The command line this process was started with, the script's path from the repository root."""
    script = Path(sys.argv[0]).resolve()
    try:
        script = script.relative_to(ROOT)
    except ValueError:
        pass
    return "python " + shlex.join([str(script), *sys.argv[1:]])


def _plain(o: Any) -> Any:
    return o.to_dict() if hasattr(o, "to_dict") else repr(o)


def write_result(benchmark: str, *, title: str, summary: str, tables: Iterable[Table] = (),
                 notes: Iterable[str] = (), command: str | None = None, data: Iterable[str] = (),
                 figures: Iterable[Figure] = (), directory: Path = RESULTS) -> Result:
    """Write a benchmark's result, the machine, today's date and the commit filled in here.

    Parameters
    ----------
    benchmark : str
        The result's name: ``directory/<benchmark>.json``.
    title, summary : str
        The page's heading, and one paragraph: what is measured and how to read it.
    tables, notes, data, figures
        As :class:`Result` holds them.
    command : str, optional
        Default: this process's command line (:func:`invocation`).
    directory : Path
        Default: ``benchmarks/results``.

    Returns
    -------
    Result
        What was written.
    """
    from _machine import machine_info  # benchmarks/ is on sys.path when a benchmark runs as a script

    commit, dirty = current_commit()
    notes, kept = list(notes), []
    for d in data:  # a result names files the repository holds; others are only mentioned
        inside = relative(Path(d))
        if Path(inside).is_absolute():
            notes.append(f"Raw output outside the repository: {d}")
        else:
            kept.append(inside)
    if dirty:
        notes.append(f"The working tree differed from {commit} (uncommitted changes) when this ran.")
    fields = dict(benchmark=benchmark, title=title, command=command or invocation(), machine=machine_info(),
                  date=datetime.date.today().isoformat(), commit=commit, summary=summary, tables=list(tables),
                  notes=notes, data=kept, figures=list(figures))
    try:
        result = Result(**fields)
    except ValueError:
        # an hour's numbers are not lost to a malformed cell: kept where the page does not read them
        bad = directory / f"{benchmark}.json.invalid"
        directory.mkdir(parents=True, exist_ok=True)
        bad.write_text(json.dumps(fields, default=_plain, indent=1, ensure_ascii=False) + "\n", encoding="utf-8")
        print(f"not a valid result, kept in {bad}", file=sys.stderr)
        raise
    path = save(result, directory)
    print(f"written: {path} (python benchmarks/render.py updates docs/benchmarks.md)", file=sys.stderr)
    return result


def raw_path(name: str) -> Path:
    """Where a benchmark keeps its raw output ``name`` (created on demand)."""
    RAW.mkdir(parents=True, exist_ok=True)
    return RAW / name


def relative(path: Path) -> str:
    """``path`` from the repository root, as a result's ``data`` names it (absolute if outside it)."""
    path = Path(path)
    try:
        return str((path if path.is_absolute() else ROOT / path).resolve().relative_to(ROOT))
    except ValueError:
        return str(path.resolve())


__all__ = ["Cell", "Figure", "RAW", "RESULTS", "ROOT", "Result", "SCHEMA", "Table", "current_commit", "invocation", "load",
           "load_all", "raw_path", "relative", "save", "validate", "write_result"]
