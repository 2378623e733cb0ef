"""The layout the architecture page describes: no import loop between drlyap's modules (lazy imports included), no
module over 600 lines, the verifier never imports the trainer, checking a run loads nothing of the verifier, and
--help loads no numerical code."""

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "drlyap"


def _module(path: Path) -> str:
    parts = path.relative_to(SRC.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _graph() -> dict[str, set[str]]:
    modules = {_module(p): p for p in SRC.rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        deps = set()
        for node in ast.walk(ast.parse(path.read_text())):  # every import, at the top or inside a function
            targets = []
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            deps.update(t for t in targets if t in modules and t != name)
        graph[name] = deps
    return graph


def test_no_import_loop_not_even_a_lazy_one():
    graph = _graph()
    # a package's __init__ importing its own submodules is its face, not a loop: drop package -> child edges
    # and child -> own package edges are imports of siblings through the face, so keep them
    def children_of(pkg: str) -> set[str]:
        return {d for d in graph[pkg] if d.startswith(pkg + ".")}

    edges = {m: {d for d in deps if d not in children_of(m)} for m, deps in graph.items()}
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for d in sorted(edges[m]):
            if state.get(d) == 1:
                raise AssertionError("import loop: " + " -> ".join(stack[stack.index(d):] + [d]))
            if d not in state:
                visit(d)
        stack.pop()
        state[m] = 2

    for m in sorted(edges):
        if m not in state:
            visit(m)


def test_no_module_over_600_lines():
    long = {str(p.relative_to(SRC)): n for p in SRC.rglob("*.py") if (n := len(p.read_text().splitlines())) > 600}
    assert not long


def test_the_verifier_never_imports_the_trainer_or_run_directories():
    graph = _graph()
    for name, deps in graph.items():
        if name.startswith("drlyap.verification"):
            bad = {d for d in deps if d.startswith(("drlyap.training", "drlyap.runs", "drlyap.workflows", "drlyap.cli"))}
            assert not bad, (name, bad)


def test_the_checker_shares_no_bounding_code_with_the_verifier():
    """The certificate checker's own modules import none of the code whose results it re-checks (the run directory's
    files are read through drlyap.runs, lazily, in check_run)."""
    graph = _graph()
    shared = ("drlyap.enclosures", "drlyap.networks", "drlyap.conditions", "drlyap.verification", "drlyap.closed_loop",
              "drlyap.regions")
    for name, deps in graph.items():
        if name.startswith("drlyap.checker"):
            bad = {d for d in deps if d.startswith(shared)}
            assert not bad, (name, bad)


def test_checking_a_run_loads_nothing_of_the_verifier_or_the_trainer(tmp_path):
    """Transitively, at run time: ``drlyap check``'s whole path (reading the run, rebuilding its system, re-proving
    every certificate of a region of attraction) loads no module of the verifier, its enclosures, the networks or the
    trainer."""
    import inspect

    from click.testing import CliRunner

    import handmade
    from drlyap.cli import main

    run = handmade.linear_run_dir(tmp_path / "run", delta=0.5)
    spec = f"{Path(handmade.__file__)}:small_pendulum"
    out = CliRunner().invoke(main, ["verify", str(run), "--system", spec, "--xi", "0.1,0.05", "--roa"])
    assert out.exit_code == 0, out.output
    system_file = tmp_path / "user_system.py"  # the same system, in a file that imports what a user's would
    system_file.write_text("import torch\nfrom drlyap.config import PAPER_CONDITION\n"
                           "from drlyap.systems import UncertainSystem\n\n" + inspect.getsource(handmade._pend) + "\n"
                           + inspect.getsource(handmade.small_pendulum))
    code = (f"import sys\nfrom drlyap.checker import check_run\nfrom drlyap.systems import resolve_system\n"
            f"results = check_run({str(run)!r}, resolve_system({str(system_file) + ':small_pendulum'!r}))\n"
            "print(sorted(r.name for r in results if r.ok))\n"
            "print(sorted(m for m in sys.modules if m.startswith('drlyap')))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    names, modules = (ast.literal_eval(line) for line in done.stdout.strip().splitlines()[-2:])
    assert names == ["roa", "roa-ball", "trained", "true-model"]
    shared = ("drlyap.enclosures", "drlyap.networks", "drlyap.conditions", "drlyap.verification", "drlyap.closed_loop",
              "drlyap.regions", "drlyap.training", "drlyap.workflows", "drlyap.render")
    assert not [m for m in modules if m.startswith(shared)], modules


def test_loading_and_verifying_a_run_loads_nothing_of_the_trainer(tmp_path):
    """Transitively, at run time: a run directory is read, its networks rebuilt and its condition proved again without
    any module of ``drlyap.training`` (a run is data; what its config builds lives in :mod:`drlyap.assembly`)."""
    import handmade

    run = handmade.linear_run_dir(tmp_path / "run", delta=0.5)
    spec = f"{Path(handmade.__file__)}:small_pendulum"
    code = ("import sys\nfrom drlyap.runs import load_run\nfrom drlyap.systems import resolve_system\n"
            "from drlyap.workflows.verify import verify\n"
            f"ver = verify(load_run({str(run)!r}, resolve_system({spec!r})))\nprint(ver.trained.status)\n"
            "print(sorted(m for m in sys.modules if m.startswith('drlyap')))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    status, modules = done.stdout.strip().splitlines()[-2:]
    assert status == "verified"
    assert not [m for m in ast.literal_eval(modules) if m.startswith("drlyap.training")], modules


def test_every_public_name_of_the_api_is_its_own_object():
    """One public name per function or class: no alias of another name of the API."""
    import drlyap

    seen: dict[int, str] = {}
    for name in drlyap.__all__:
        obj = getattr(drlyap, name)
        assert id(obj) not in seen, f"drlyap.{name} is drlyap.{seen.get(id(obj))}"
        seen[id(obj)] = name


def test_help_loads_no_numerical_code():
    code = "import sys; from drlyap.cli import main; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
    for command in (["--help"], ["train", "--help"], ["sweep", "--help"], ["rl", "train", "--help"]):
        code = (f"import sys; from drlyap.cli import main\ntry:\n    main({command!r})\nexcept SystemExit:\n    pass\n"
                "print('torch' in sys.modules, file=sys.stderr)")
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
        assert out.stderr.strip().splitlines()[-1] == "False", (command, out.stderr)


def test_the_command_reference_lists_every_option():
    """docs/cli.md stays true: every command and every option of it appears there."""
    import click

    from drlyap.cli import main

    text = (ROOT / "docs" / "cli.md").read_text()

    def walk(cmd, path):
        yield path, cmd
        if isinstance(cmd, click.Group):
            for name, sub in cmd.commands.items():
                yield from walk(sub, [*path, name])

    missing = []
    for path, cmd in walk(main, []):
        if path and f"## drlyap {' '.join(path)}" not in text and not isinstance(cmd, click.Group):
            missing.append(" ".join(path))
        for param in cmd.params:
            missing += [f"{' '.join(path)} {opt}" for opt in param.opts if opt.startswith("--") and opt not in text]
    assert not missing, f"docs/cli.md lacks {missing}: regenerate it from --help"


@pytest.mark.parametrize("args, message", [
    (["train", "nosuchsystem", "--out", "OUT"], "unknown system 'nosuchsystem'; valid: cartpole"),
    (["train", "missing.py:make", "--out", "OUT"], "missing.py does not exist"),
    (["train", "pendulum", "--iters", "-1", "--out", "OUT"], "iters = -1 (must be >= 1)"),
    (["train", "pendulum", "--eps", "2", "--out", "OUT"], "risk_level = 2.0 (must be in (0, 1))"),
    (["train", "pendulum", "--out", "TAKEN"], "already exists"),
    (["verify", "/nonexistent"], "run directory /nonexistent does not exist"),
    (["evaluate", "TAKEN", "--xi", "0"], "no run.json"),
    (["compare", "TAKEN", "--xi", "0"], "no run.json"),
    (["check", "TAKEN", "--system", "nosuchsystem"], "unknown system 'nosuchsystem'"),
])
def test_a_bad_argument_is_refused_before_the_numerical_code_loads(tmp_path, args, message):
    """A command that only reports a bad argument answers at once: it imports no torch."""
    (tmp_path / "taken").mkdir()
    args = [str(tmp_path / "out") if a == "OUT" else str(tmp_path / "taken") if a == "TAKEN" else a for a in args]
    code = (f"import sys; from drlyap.cli import main\ntry:\n    main({args!r})\nexcept SystemExit as exit:\n"
            "    print(exit.code, 'torch' in sys.modules, file=sys.stderr)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=tmp_path)
    *lines, last = out.stderr.strip().splitlines()
    assert last == "1 False", out.stderr
    assert len(lines) == 1 and lines[0].startswith("Error: ") and message in lines[0], out.stderr
    assert not (tmp_path / "out").exists()


def test_the_names_checked_without_imports_are_the_registry_s():
    code = ("import sys; from drlyap.specs import BUILT_IN; from drlyap.systems import system_names\n"
            "print(sorted(BUILT_IN) == system_names())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "True"


def _table(page: str, header: str) -> list[list[str]]:
    """The rows of the markdown table whose header row starts with ``header`` (cells stripped)."""
    lines = page.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(f"| {header} |"))
    joined: list[str] = []
    for line in lines[start + 2:]:
        if not line.strip():
            break
        if line.startswith("|"):
            joined.append(line)
        else:  # a row written over two lines
            joined[-1] += " " + line
    return [[cell.strip() for cell in row.strip().strip("|").split(" | ")] for row in joined]


def _names(cell: str) -> list[str]:
    return re.findall(r"`([^`]+)`", cell)


def _defined() -> set[str]:
    """Every class and function defined in drlyap, and every module-level assigned name."""
    names = set()
    for path in SRC.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.ClassDef, ast.FunctionDef)):
                names.add(node.name)
            elif isinstance(node, (ast.Assign, ast.AnnAssign)):
                targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                names.update(t.id for t in targets if isinstance(t, ast.Name))
    return names


def test_the_architecture_page_names_what_exists_and_every_module():
    """The page's layer table lists every top-level module and package of drlyap and names only modules that exist
    (its parenthesised module names too); its objects live where it says; the classes its words table names exist."""
    page = (ROOT / "docs" / "architecture.md").read_text()
    modules = {p.stem for p in SRC.rglob("*.py")} | {p.name for p in SRC.rglob("*") if p.is_dir()}
    defined = _defined()
    listed = set()
    for _, cell, what in _table(page, "layer"):
        for name in _names(cell):
            path = SRC / name.rstrip("/")
            assert path.with_suffix(".py").exists() or path.is_dir(), f"the layer table names {name}, not in drlyap"
            listed.add(name.rstrip("/"))
        for name in _names(what):
            if re.fullmatch(r"[a-z_]+/?", name):  # a module, or a function the row names
                assert name.rstrip("/") in modules | defined, f"the layer table names {name}, not in drlyap"
    top = {p.stem for p in SRC.glob("*.py") if p.stem != "__init__"} | {
        p.name for p in SRC.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert top <= listed, f"modules the layer table does not list: {sorted(top - listed)}"
    for objects, where, _ in _table(page, "object"):
        files = [f for w in _names(where) for f in ((SRC / w).rglob("*.py") if (SRC / w).is_dir() else [SRC / w])]
        sources = "\n".join(f.read_text() for f in files)
        for name in _names(objects):
            assert re.search(rf"^class {name}\b", sources, re.M), f"{name} is not defined in {where}"
    for row in _table(page, "word"):
        for name in _names(" ".join(row[1:])):
            for part in name.split("."):
                if re.fullmatch(r"[A-Z][A-Za-z]+", part):
                    assert part in defined, f"the words table names {name}, not defined in drlyap"


def test_a_built_in_system_holds_physics_and_takes_its_recipe_from_recipes():
    """The built-in systems' training recipes live in drlyap.recipes (which loads no torch, so --help quotes them);
    the systems take them from there."""
    from drlyap.recipes import RECIPES, defaults_text
    from drlyap.specs import BUILT_IN
    from drlyap.systems import get_system

    assert set(RECIPES) == set(BUILT_IN)
    for name in BUILT_IN:
        assert get_system(name).defaults is RECIPES[name]
    assert "exit_margin" not in (SRC / "systems" / "library.py").read_text()
    assert defaults_text("iters") == "3000; 9000 for quadrotor2d"
    assert defaults_text("roa_boxes", unset="verify_boxes").endswith("8,000,000 for quadrotor2d")
    done = subprocess.run([sys.executable, "-c", "import sys, drlyap.recipes; print('torch' in sys.modules)"],
                          capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "False"
