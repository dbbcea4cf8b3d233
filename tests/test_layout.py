"""The architecture the folders promise: one-way dependencies, no import cycles, a light client.

Imports are read from the source (AST), so a module imported lazily inside a function counts
as a dependency as much as one at the top: the direction must hold for both.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CODE = ("config", "estimator", "drivers", "service")
# Which top-level parts each may import (service → drivers → estimator; config beside them).
ALLOWED = {
    "estimator": {"estimator"},
    "config": {"config"},
    "drivers": {"drivers", "estimator", "config"},
    "service": {"service", "drivers", "estimator", "config"},
}


def _modules() -> dict[str, Path]:
    found = {}
    for part in CODE:
        for path in (REPO / part).rglob("*.py"):
            rel = path.relative_to(REPO).with_suffix("")
            parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
            found["vtolpose." + ".".join(parts)] = path
    return found


def _imports(path: Path, module: str, is_package: bool) -> set[str]:
    """Every vtolpose module this file imports (``from pkg import name`` counts name if a module)."""
    names = set()
    package = module if is_package else module.rsplit(".", 1)[0]
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1] + ([base] if base else []))
            names.add(base)
            names.update(f"{base}.{alias.name}" for alias in node.names)
    return {n for n in names if n.startswith("vtolpose.")}


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    graph = {}
    for name, path in modules.items():
        deps = _imports(path, name, path.name == "__init__.py")
        graph[name] = {d for d in deps if d in modules and d != name}
    return graph


def test_dependencies_point_one_way():
    wrong = []
    for module, deps in _graph().items():
        part = module.split(".")[1]
        wrong += [f"{module} imports {d}" for d in deps if d.split(".")[1] not in ALLOWED[part]]
    assert wrong == []


def test_no_import_cycles():
    graph = _graph()
    # A package's __init__ importing its own sub-modules is not a cycle unless they import it back.
    state: dict[str, int] = {}
    cycles = []

    def visit(node: str, stack: list[str]) -> None:
        state[node] = 1
        for dep in sorted(graph[node]):
            if node.startswith(dep + "."):
                continue  # a module naming its own package (parent __init__ runs first anyway)
            if state.get(dep) == 1:
                cycles.append(stack[stack.index(dep):] + [dep])
            elif dep not in state:
                visit(dep, stack + [dep])
        state[node] = 2

    for module in sorted(graph):
        if module not in state:
            visit(module, [module])
    assert cycles == []


def test_every_sub_package_says_what_it_owns():
    for init in sorted(p for part in CODE for p in (REPO / part).rglob("__init__.py")):
        doc = ast.get_docstring(ast.parse(init.read_text(encoding="utf-8")))
        assert doc and len(doc) > 40, f"{init.relative_to(REPO)} has no docstring saying what it owns"


def printed_by_a_fresh_process(code: str) -> str:
    """What ``code`` prints in a new interpreter (nothing imported yet): for what an import pulls in."""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO.parent)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def test_the_mapper_client_imports_without_opencv_or_the_estimator():
    code = ("import sys; import vtolpose.client; "
            "heavy = sorted(m for m in sys.modules if m.split('.')[0] in ('cv2', 'scipy') "
            "or m.startswith(('vtolpose.estimator.filter', 'vtolpose.estimator.vision'))); print(heavy)")
    assert printed_by_a_fresh_process(code) == "[]"


def test_the_command_line_and_a_runtime_without_camera_do_not_load_opencv() -> None:
    # OpenCV costs a process ~16 MB and up to a second to import: only camera work may load it.
    code = ("import sys; from vtolpose.service.cli import build_parser; build_parser(); "
            "import vtolpose.service.runtime.daemon, vtolpose.service.replay.session, vtolpose.service.bench.runner; "
            "print('cv2' in sys.modules)")
    assert printed_by_a_fresh_process(code) == "False"


def test_a_live_service_loads_no_kernel_of_runs_and_a_replay_loads_them_all() -> None:
    # A live service (an output, so the present pose is wanted) goes sample by sample: the kernels of runs
    # of samples, ~5 MB loaded, stay out of it; an offline replay's runtime has them ready before its first sample.
    code = ("from vtolpose.config import load_config; "
            "from vtolpose.estimator.core.calibration import Calibration, ImuCalibration, ImuNoise; "
            "from vtolpose.service.runtime.daemon import build_runtime; "
            "from vtolpose.estimator.inertial import propagation_kernel as p, sample_kernel as s; "
            "cal = Calibration(ImuCalibration(200.0, ImuNoise(1e-3, 1e-2, 1e-5, 1e-4))); "
            "live = %s; "
            "cfg = load_config(None, {'outputs': {'mavlink': {'enabled': live, 'url': 'udpout:127.0.0.1:9'}}}); "
            "runtime = build_runtime(cfg, cal); "
            "print(runtime.fuses_runs, [bool(k.signatures) for k in (p.step_run, p.step_all_run, s.downsample_run, "
            "s.stillness_run, s.level_run, s.plain_run, s.to_time, p.step, p.step_all, s.screen_rows)])")
    assert printed_by_a_fresh_process(code % True) == "False " + str([False] * 7 + [True] * 3)
    assert printed_by_a_fresh_process(code % False) == "True " + str([True] * 10)


def test_the_estimator_imports_no_scipy_sub_package() -> None:
    # numba imports scipy's top package (~1 MB) to look for its BLAS; scipy.special would add ~20 MB.
    code = ("import sys; import vtolpose.estimator.filter, vtolpose.estimator.metrics; "
            "print(sorted(m for m in sys.modules if m.startswith('scipy.') and m.split('.')[1][0] != '_'"
            " and m != 'scipy.version'))")
    assert printed_by_a_fresh_process(code) == "[]"


def _estimator_imports(path: Path) -> list[str]:
    """What ``path`` takes from the estimator that is not one of its public names."""
    from vtolpose.estimator._public import PUBLIC

    wrong = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            wrong += [a.name for a in node.names if a.name.startswith("vtolpose.estimator")]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if node.module.startswith("vtolpose.estimator."):
                wrong.append(node.module)
            elif node.module == "vtolpose.estimator":
                wrong += [f"vtolpose.estimator.{a.name}" for a in node.names if a.name not in PUBLIC]
    return wrong


def test_service_takes_only_the_estimators_public_names():
    wrong = {str(p.relative_to(REPO)): w for p in [*sorted((REPO / "service").rglob("*.py")), REPO / "client.py"]
             if (w := _estimator_imports(p))}
    assert wrong == {}, "import these through vtolpose.estimator (its public names: estimator/_public.py)"


def test_the_check_sees_a_private_import(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text("from vtolpose.estimator.filter import Estimator\nfrom vtolpose.estimator import _hidden\n")
    assert _estimator_imports(probe) == ["vtolpose.estimator.filter", "vtolpose.estimator._hidden"]


def test_every_public_name_resolves_to_its_module():
    import importlib

    import vtolpose.estimator as estimator
    from vtolpose.estimator._public import PUBLIC

    for name, module in PUBLIC.items():
        owner = importlib.import_module(module)
        expected = getattr(owner, name) if hasattr(owner, name) else importlib.import_module(f"{module}.{name}")
        assert getattr(estimator, name) is expected, name


# The flat ``{"a.b": value}`` configuration is read in config/ and in the wiring only; the rest takes typed
# sections (config/sections.py) or options built there, so a key renamed in the schema cannot be missed.
FLAT_CONFIG_READERS = ("config", "service/runtime/wiring.py")
_LOOKUP_CALLS = {"get", "pop", "setdefault", "startswith"}


def _looks_like_a_key(node: ast.AST) -> bool:
    """A string (or an f-string's start) of the form ``section.name``, ``section.`` being a schema section."""
    from vtolpose.config.schema import SCHEMA

    if isinstance(node, ast.JoinedStr):
        node = node.values[0] if node.values else node
    if not (isinstance(node, ast.Constant) and isinstance(node.value, str)):
        return False
    section, dot, rest = node.value.partition(".")
    return bool(dot) and section in {k.split(".")[0] for k in SCHEMA} and all(
        part.isidentifier() for part in rest.rstrip(".").split(".") if rest)


def _flat_config_lookups(path: Path) -> list[str]:
    """``cfg["a.b"]``, ``cfg.get("a.b")``, ``get(cfg, "a")``, ``k.startswith("a.b.")`` and the like in ``path``,
    and an import of :func:`vtolpose.config.get` (a section by its prefix, dotted or not)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.module == "vtolpose.config" and "get" in [a.name for a in node.names]:
            found.append(f"line {node.lineno}: {ast.unparse(node)}")
        elif isinstance(node, ast.Subscript) and _looks_like_a_key(node.slice):
            found.append(f"line {node.lineno}: {ast.unparse(node)}")
        elif isinstance(node, ast.Call):
            name = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
            if name in _LOOKUP_CALLS and any(_looks_like_a_key(arg) for arg in node.args):
                found.append(f"line {node.lineno}: {ast.unparse(node)}")
    return found


def test_only_config_and_the_wiring_read_the_flat_configuration():
    files = [p for part in ("service", "drivers") for p in sorted((REPO / part).rglob("*.py"))] + [REPO / "client.py"]
    readers = [REPO / r for r in FLAT_CONFIG_READERS]
    found = {str(p.relative_to(REPO)): hits for p in files
             if not any(p == r or r in p.parents for r in readers) and (hits := _flat_config_lookups(p))}
    assert found == {}, "take a section from config/sections.py (built in service/runtime/wiring.py) instead"


def test_the_check_sees_every_spelling_of_a_flat_lookup(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text("\n".join([
        "a = cfg['sensors.gps.type']", 'b = cfg["outputs.zenoh.tls.mutual"]', "c = cfg.get('vehicle.system_id')",
        "d = get(cfg, 'estimator.init')", "e = cfg[f'smoothing.{k}']", "f = [k for k in cfg if k.startswith('sensors.imu.')]",
        "from vtolpose.config import ConfigError, get",
        # not look-ups: a message, a key named in a check's error, a dotted name that is no configuration section
        "log.warning('outputs.ros2: a message')", "g = check('outputs.ros2.namespace', name)", "h = row['t.s']",
    ]))
    assert sorted(int(hit.split(":")[0].split()[1]) for hit in _flat_config_lookups(probe)) == [1, 2, 3, 4, 5, 6, 7]
