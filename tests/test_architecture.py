"""The layout's rules, checked by parsing every module's imports (function-level and TYPE_CHECKING
imports included): data flows one way, sources -> transforms -> writer -> validate.

Each rule is also run on a small package with a known violation, so a checker that finds nothing
cannot pass silently.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "src" / "ncore_convert"


def module_name(root: Path, path: Path) -> str:
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def parse_package(root: Path) -> dict[str, ast.Module]:
    return {module_name(root, p): ast.parse(p.read_text(), str(p)) for p in sorted(root.rglob("*.py"))}


def imports_of(name: str, tree: ast.Module, modules: set[str], is_package: bool) -> set[str]:
    """The package's modules that ``name`` imports anywhere in its body (``from pkg import module``
    counts as importing the module; ``from pkg import symbol`` as importing ``pkg``)."""
    top = name.split(".")[0]
    package = name if is_package else name.rpartition(".")[0]
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name.split(".")[0] == top)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != top:
                continue
            for alias in node.names:
                out.add(f"{target}.{alias.name}" if f"{target}.{alias.name}" in modules else target)
    return {m for m in out if m in modules and m != name}


def import_graph(root: Path) -> tuple[dict[str, set[str]], dict[str, ast.Module]]:
    trees = parse_package(root)
    packages = {module_name(root, p) for p in root.rglob("__init__.py")}
    modules = set(trees)
    return {name: imports_of(name, tree, modules, name in packages) for name, tree in trees.items()}, trees


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def under(module: str, *prefixes: str) -> bool:
    return any(module == p or module.startswith(p + ".") for p in prefixes)


#: (modules the rule applies to, modules they must not import), as prefixes below the package.
LAYER_RULES = [
    (("transforms",), ("sources", "converters", "writer", "validate", "run")),
    (("sources",), ("converters", "writer", "validate", "run", "storage")),
    # the runner is dataset-agnostic: a dataset reader's internals reach it only through the tasks
    (("run",), ("sources",)),
    (("validate", "preview", "evaluate"), ("converters",)),
    # the read-back views (NCore seen as a dataset's own layout) and the converters stay apart
    (("views",), ("converters", "writer", "run")),
    (("converters", "sources", "transforms", "writer", "validate", "run"), ("views",)),
]


def layer_violations(graph: dict[str, set[str]], top: str) -> list[str]:
    out = []
    for owners, forbidden in LAYER_RULES:
        owners_full = tuple(f"{top}.{o}" for o in owners)
        forbidden_full = tuple(f"{top}.{f}" for f in forbidden)
        for module, imported in graph.items():
            if under(module, *owners_full):
                out += [f"{module} imports {m}" for m in sorted(imported) if under(m, *forbidden_full)]
    return out


#: ``transforms/`` by subject, in the order they may import each other: the shared modules loose at
#: the top (geometry, time base, noise, ...), then each subpackage, which may import only the shared
#: modules and the subpackages before it.
TRANSFORM_SUBJECTS = ("objects", "camera", "lidar")
MAX_LOOSE_TRANSFORMS = 6  #: modules loose at the top of transforms/ (the shared ones)


def transform_rank(module: str, top: str) -> int | None:
    """0 for a shared module of ``transforms/``, 1 + its index in ``TRANSFORM_SUBJECTS`` for one in a
    subject's subpackage, None outside ``transforms/`` (or for the package itself)."""
    if not module.startswith(f"{top}.transforms."):
        return None
    subject = module.split(".")[2]
    return TRANSFORM_SUBJECTS.index(subject) + 1 if subject in TRANSFORM_SUBJECTS else 0


def transform_layer_violations(graph: dict[str, set[str]], top: str) -> list[str]:
    """Imports inside ``transforms/`` against the subject order (``TRANSFORM_SUBJECTS``)."""
    out = []
    for module, imported in graph.items():
        rank = transform_rank(module, top)
        if rank is None:
            continue
        for m in sorted(imported):
            other = transform_rank(m, top)
            if other is not None and other > rank:
                out.append(f"{module} imports {m}")
    return out


def loose_transforms(root: Path) -> list[str]:
    """The modules at the top of ``transforms/`` (not in a subject's subpackage), ``__init__`` aside."""
    return sorted(p.stem for p in (root / "transforms").glob("*.py") if p.stem != "__init__")


MAX_MODULE_LINES = 450
#: why a module over the limit is split, not excused (the message of the size rule)
SPLIT_ADVICE = (
    "split it where its subjects part (one algorithm, one reader, one stage per module), as writer/ and"
    " converters/*/inputs.py were; do not raise the limit or list the module as an exception: a module"
    " this long is read by scrolling, and what it mixes is imported together"
)


def oversized_modules(root: Path, limit: int = MAX_MODULE_LINES) -> dict[str, int]:
    """Modules of the package at ``root`` longer than ``limit`` lines: module -> lines."""
    out = {}
    for path in sorted(root.rglob("*.py")):
        lines = len(path.read_text().splitlines())
        if lines > limit:
            out[module_name(root, path)] = lines
    return out


def ncore_writer_users(trees: dict[str, ast.Module]) -> set[str]:
    """Modules that import an NCore writer class or use a component's ``.Writer``."""
    users = set()
    for name, tree in trees.items():
        for node in ast.walk(tree):
            imported = isinstance(node, ast.ImportFrom) and (node.module or "").startswith("ncore.")
            if imported and any("Writer" in a.name for a in node.names):
                users.add(name)
            if isinstance(node, ast.Attribute) and node.attr == "Writer":
                users.add(name)
    return users


def loader_constructors(trees: dict[str, ast.Module]) -> set[str]:
    """Modules that call ``SequenceLoaderV4(...)``."""
    out = set()
    for name, tree in trees.items():
        for node in ast.walk(tree):
            if isinstance(node, ast.Call):
                func = node.func
                called = func.id if isinstance(func, ast.Name) else getattr(func, "attr", None)
                if called == "SequenceLoaderV4":
                    out.add(name)
    return out


def torch_importers(trees: dict[str, ast.Module]) -> set[str]:
    """Modules that import torch (at any level)."""
    out = set()
    for name, tree in trees.items():
        for node in ast.walk(tree):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else []
            names += [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            if any(n == "torch" or n.startswith("torch.") for n in names):
                out.add(name)
    return out


#: av2's ``x_SE3_y`` names (maps y to x); past the AV2 reader every transform is ``T_a_b`` (a -> b).
AV2_TRANSFORM_NAME = re.compile(r"^[A-Za-z]+_SE3_[A-Za-z]+")


def av2_transform_names(trees: dict[str, ast.Module]) -> dict[str, set[str]]:
    """Identifiers (variables, attributes, arguments, functions, classes) named like ``city_SE3_ego``."""
    out: dict[str, set[str]] = {}
    for name, tree in trees.items():
        for node in ast.walk(tree):
            ident = (
                getattr(node, "id", None)
                or (node.attr if isinstance(node, ast.Attribute) else None)
                or (node.arg if isinstance(node, ast.arg) else None)
                or (node.name if isinstance(node, ast.FunctionDef | ast.ClassDef) else None)
            )
            if isinstance(ident, str) and AV2_TRANSFORM_NAME.match(ident):
                out.setdefault(name, set()).add(ident)
    return out


def _is_z(node: ast.expr) -> bool:
    """``xyz[:, 2]``, ``points[..., 2]`` or a name like ``z`` / ``depth``: a point's depth."""
    if isinstance(node, ast.Subscript):
        last = node.slice.elts[-1] if isinstance(node.slice, ast.Tuple) else node.slice
        return isinstance(last, ast.Constant) and last.value == 2
    return isinstance(node, ast.Name) and node.id in ("z", "depth", "z_m", "depth_m")


def _is_abs_within(node: ast.expr) -> bool:
    """``np.abs(local) <= half``: a point-in-box (or cube) comparison."""
    return (
        isinstance(node, ast.Compare)
        and isinstance(node.left, ast.Call)
        and isinstance(node.left.func, ast.Attribute)
        and node.left.func.attr == "abs"
        and any(isinstance(op, ast.LtE) for op in node.ops)
    )


def own_geometry(trees: dict[str, ast.Module], owners: tuple[str, ...]) -> dict[str, set[str]]:
    """Modules under ``owners`` that compute a camera projection of their own (a product divided by a
    point's depth: ``fx * x / z``) or a box test (``np.all(np.abs(local) <= half, ...)`` or
    ``(np.abs(...) <= ...).all(...)``), with the line of each; the kernel in ``transforms/`` is
    where those live."""
    out: dict[str, set[str]] = {}
    for name, tree in trees.items():
        if not under(name, *owners):
            continue
        for node in ast.walk(tree):
            if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div):
                if isinstance(node.left, ast.BinOp) and isinstance(node.left.op, ast.Mult) and _is_z(node.right):
                    out.setdefault(name, set()).add(f"projection at line {node.lineno}")
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "all":
                tested = node.args[:1] if node.args else [node.func.value]
                if any(_is_abs_within(arg) for arg in tested):
                    out.setdefault(name, set()).add(f"box test at line {node.lineno}")
    return out


#: the box-geometry kernel: the only module that writes a slab test or a box's corner table
BOX_KERNEL = "ncore_convert.transforms.objects.boxes"
MIN_LIKE, MAX_LIKE = {"fmin", "minimum", "min", "nanmin"}, {"fmax", "maximum", "max", "nanmax"}
CORNER_NAMES = {"CORNER_SIGNS", "BOX_EDGES"}


def _call_name(node: ast.Call) -> str | None:
    func = node.func
    return func.attr if isinstance(func, ast.Attribute) else func.id if isinstance(func, ast.Name) else None


def _pairs(scope: ast.AST, names: set[str]) -> dict[frozenset[str], int]:
    """The unordered argument pairs (as source dumps) of the calls to ``names`` in ``scope`` -> a line."""
    out = {}
    for node in ast.walk(scope):
        if isinstance(node, ast.Call) and _call_name(node) in names and len(node.args) >= 2:
            out.setdefault(frozenset(ast.dump(a) for a in node.args[:2]), node.lineno)
    return out


def _is_sign_pair(node: ast.expr) -> bool:
    """A literal pair of opposite numbers, ``(-1, 1)`` or ``[-0.5, 0.5]``: one axis of a corner table."""
    if not isinstance(node, ast.Tuple | ast.List) or len(node.elts) != 2:
        return False
    try:
        a, b = (ast.literal_eval(e) for e in node.elts)
    except ValueError:
        return False
    return isinstance(a, int | float) and isinstance(b, int | float) and a == -b != 0


def own_box_geometry(trees: dict[str, ast.Module]) -> dict[str, set[str]]:
    """Modules other than the kernel (``BOX_KERNEL``) that write a slab test (in one function, the
    min and the max of the same two ray parameters: where a ray enters and leaves a slab) or a box's
    corner table (three nested loops over a sign pair, ``product(..., repeat=3)``, or the kernel's
    own tables by name), with the line of each."""
    out: dict[str, set[str]] = {}
    for name, tree in trees.items():
        if name == BOX_KERNEL:
            continue
        scopes = [n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)] + [tree]
        for scope in scopes:
            lows, highs = _pairs(scope, MIN_LIKE), _pairs(scope, MAX_LIKE)
            for pair in lows.keys() & highs.keys():
                out.setdefault(name, set()).add(f"slab test at line {min(lows[pair], highs[pair])}")
        for node in ast.walk(tree):
            if isinstance(node, ast.comprehension | ast.GeneratorExp | ast.ListComp):
                generators = getattr(node, "generators", [])
                if sum(_is_sign_pair(g.iter) for g in generators) >= 3:
                    out.setdefault(name, set()).add(f"corner table at line {node.lineno}")
            if isinstance(node, ast.Call) and _call_name(node) == "product":
                if any(k.arg == "repeat" and getattr(k.value, "value", None) == 3 for k in node.keywords):
                    out.setdefault(name, set()).add(f"corner table at line {node.lineno}")
            ident = getattr(node, "id", None) or (node.attr if isinstance(node, ast.Attribute) else None)
            if ident in CORNER_NAMES or (isinstance(node, ast.alias) and node.name in CORNER_NAMES):
                out.setdefault(name, set()).add(f"corner table at line {getattr(node, 'lineno', 0)}")
    return out


def calls_to(trees: dict[str, ast.Module], name: str, keyword: str | None = None) -> dict[str, int]:
    """Modules that call ``name`` (a function, method or class; with ``keyword`` among the call's
    keywords, if given) -> how many times."""
    out: dict[str, int] = {}
    for module, tree in trees.items():
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and _call_name(node) == name:
                if keyword is None or any(k.arg == keyword for k in node.keywords):
                    out[module] = out.get(module, 0) + 1
    return out


def counter_classes(trees: dict[str, ast.Module]) -> set[str]:
    """Modules that define a counter: a class deriving from ``Tally`` directly."""
    return {
        module
        for module, tree in trees.items()
        for node in ast.walk(tree)
        if isinstance(node, ast.ClassDef) and any(getattr(b, "id", None) == "Tally" for b in node.bases)
    }


def one_site_per_converter(found: dict[str, int]) -> dict[str, int]:
    """Of ``calls_to``'s answer, the converter packages (``converters.<dataset>``) that make the call
    in more than one place: dataset -> call sites."""
    sites: dict[str, int] = {}
    for module, n in found.items():
        parts = module.split(".")
        if parts[1:2] == ["converters"] and len(parts) > 3:
            sites[parts[2]] = sites.get(parts[2], 0) + n
    return {dataset: n for dataset, n in sites.items() if n > 1}


#: Constructors of state shared by the functions of a module (locks, pools, events).
SHARED_STATE_CALLS = {"Lock", "RLock", "Semaphore", "Event", "Condition", "ThreadPoolExecutor", "ProcessPoolExecutor"}
#: Methods that change a container in place.
MUTATORS = {"append", "extend", "add", "update", "clear", "pop", "popitem", "setdefault", "remove", "discard", "insert"}


def _called_name(node: ast.AST) -> str | None:
    if isinstance(node, ast.Call):
        return node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", None)
    return None


def _is_environ(node: ast.AST) -> bool:
    return isinstance(node, ast.Attribute) and node.attr == "environ" or getattr(node, "id", None) == "environ"


def module_state(trees: dict[str, ast.Module], prefix: str) -> dict[str, set[str]]:
    """Per module under ``prefix``: module-level locks and pools, module-level names that a function
    changes (``global``, item or attribute assignment, a mutating method), and environment writes."""
    out: dict[str, set[str]] = {}
    for module, tree in trees.items():
        if not under(module, prefix):
            continue
        found = set()
        names = set()
        for node in tree.body:
            targets = (
                node.targets
                if isinstance(node, ast.Assign)
                else [node.target]
                if isinstance(node, ast.AnnAssign)
                else []
            )
            value = getattr(node, "value", None)
            for target in targets:
                if isinstance(target, ast.Name):
                    names.add(target.id)
                    if _called_name(value) in SHARED_STATE_CALLS:
                        found.add(f"{target.id}: a module-level {_called_name(value)}")
        for node in ast.walk(tree):
            if isinstance(node, ast.Global):
                found.update(f"{n}: rebound by a function (global)" for n in node.names)
            elif isinstance(node, ast.Assign | ast.AugAssign | ast.AnnAssign):
                for target in node.targets if isinstance(node, ast.Assign) else [node.target]:
                    base = target.value if isinstance(target, ast.Subscript | ast.Attribute) else None
                    if base is not None and _is_environ(base):
                        found.add("os.environ: written")
                    elif isinstance(base, ast.Name) and base.id in names:
                        found.add(f"{base.id}: changed by a function")
            elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
                owner = node.func.value
                if node.func.attr in MUTATORS and _is_environ(owner) or node.func.attr == "putenv":
                    found.add("os.environ: written")
                elif node.func.attr in MUTATORS and isinstance(owner, ast.Name) and owner.id in names:
                    found.add(f"{owner.id}: changed by a function")
        if found:
            out[module] = found
    return out


@pytest.fixture(scope="module")
def project():
    return import_graph(PACKAGE)


def test_the_input_side_keeps_no_module_state(project):
    """``sources/`` holds no module-level lock, pool, counter or container that functions change,
    and writes no environment variable: a reader's state lives in its ``Reader`` (issue 72)."""
    _, trees = project
    assert module_state(trees, "ncore_convert.sources") == {}


def test_no_import_cycles(project):
    graph, _ = project
    assert cycles(graph) == []


def test_layers_import_only_downstream(project):
    graph, _ = project
    assert layer_violations(graph, "ncore_convert") == []


def test_transforms_import_by_subject(project):
    """The shared transforms import no subject; objects (the box kernel) no camera or lidar code; the
    camera no lidar code; the lidar may use all of them."""
    graph, _ = project
    assert transform_layer_violations(graph, "ncore_convert") == []


def test_transforms_are_grouped_by_subject():
    loose = loose_transforms(PACKAGE)
    assert len(loose) <= MAX_LOOSE_TRANSFORMS, f"{len(loose)} modules loose in transforms/: {loose}"


def test_no_module_is_over_the_size_limit():
    too_long = oversized_modules(PACKAGE)
    assert too_long == {}, f"modules over {MAX_MODULE_LINES} lines: {too_long}; {SPLIT_ADVICE}"


def test_only_the_writer_talks_to_the_ncore_writer(project):
    _, trees = project
    assert {m for m in ncore_writer_users(trees) if not under(m, "ncore_convert.writer")} == set()


def test_only_readback_opens_sequences(project):
    _, trees = project
    assert loader_constructors(trees) == {"ncore_convert.validate.readback"}


def test_av2_transform_names_stay_in_the_av2_reader(project):
    _, trees = project
    readers = ("ncore_convert.sources.argoverse2", "ncore_convert.sources.argoverse2_annotations")
    found = set(av2_transform_names(trees))
    assert found and found - set(readers) == set()


def test_the_conversion_never_imports_torch(project):
    """Only the preview (NCore's camera models run on torch) and the opt-in ``Dataset`` adapter
    import torch."""
    _, trees = project
    assert torch_importers(trees) == {"ncore_convert.preview", "ncore_convert.views.opencood_torch"}


def test_projection_and_box_tests_live_in_the_kernel(project):
    """The converters plan and hand over, and the validators and synthetic renderers use the same
    geometry: every projection and box test is the kernel's (``transforms/``: ``Pinhole.project``,
    ``boxes.PointGrid`` / ``boxes.in_box``, the depth buffer)."""
    _, trees = project
    found = own_geometry(trees, ("ncore_convert",))
    assert {module for module in found if not under(module, "ncore_convert.transforms")} == set()


def test_box_geometry_lives_in_one_kernel(project):
    """Corners, near-plane cuts, the slab test and points in boxes are written once, in
    ``transforms/objects/boxes.py``; every other module calls it."""
    _, trees = project
    assert own_box_geometry(trees) == {}


def test_shared_steps_are_written_once(project):
    """What both converters do is one helper: a dataset builds its camera views in one place (the
    lidar colours and the labels share them; ``ColourFrame.of`` adds the picture), every lidar frame
    is stored through ``converters.common.LidarStore``, the counters are ``converters.common.Counts``,
    and the read side takes every pose from ``validate.poses``."""
    _, trees = project
    assert one_site_per_converter(calls_to(trees, "CameraView")) == {}
    assert set(calls_to(trees, "ColourFrame")) == set()
    stores = {m for m in calls_to(trees, "store_frame", "model_element") if not under(m, "ncore_convert.writer")}
    assert stores == {"ncore_convert.converters.common"}
    assert counter_classes(trees) == {"ncore_convert.converters.common"}
    assert set(calls_to(trees, "evaluate_poses")) == {"ncore_convert.validate.poses"}


def test_the_checks_find_known_violations(tmp_path):
    """Negative control: a package with a function-level cycle, a TYPE_CHECKING cycle, an upward
    import, a view importing a converter and a converter a view, a stray writer use, a stray loader
    and an av2 name past the reader."""
    pkg = tmp_path / "ncore_convert"
    files = {
        "__init__.py": "",
        "transforms/__init__.py": "",
        "transforms/geo.py": "def f():\n    from ncore_convert.sources import reader\n    city_SE3_ego = 1\n",
        "sources/__init__.py": "",
        "sources/reader.py": "from ncore_convert.transforms import geo\n",
        "converters/__init__.py": "",
        "converters/a.py": (
            "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from ncore_convert.converters.b import B\n"
        ),
        "converters/b.py": (
            "from ncore_convert.converters import a\nfrom ncore.data.v4 import SequenceComponentGroupsWriter\n"
        ),
        "validate/__init__.py": "",
        "validate/check.py": "from ncore_convert.converters.a import x\nloader = SequenceLoaderV4(reader)\n",
        "views/__init__.py": "",
        "views/look.py": "from ncore_convert.validate import check\nfrom ncore_convert.converters import b\n",
        "converters/c.py": "def g():\n    from ncore_convert.views import look\n    import torch.nn\n",
        "converters/d.py": (
            "u = fx * xyz[:, 0] / xyz[:, 2] + cx\ninside = np.all(np.abs(local) <= half, axis=1)\n"
            "near = (np.abs(p - c) <= r).all(axis=1)\nt = (g - o[:, 2]) / d[:, 2]\n"
        ),
        # a slab test, a corner table, the kernel's table by name, and transforms importing upwards
        "converters/slab.py": (
            "def enter(o, d, lo, hi):\n    t1, t2 = (lo - o) / d, (hi - o) / d\n"
            "    return np.fmax(np.fmin(t1, t2), 0), np.fmin(np.fmax(t1, t2), 9)\n"
        ),
        "validate/corners.py": (
            "signs = [(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]\n"
            "from ncore_convert.transforms.objects.boxes import CORNER_SIGNS\n"
        ),
        "transforms/objects/__init__.py": "",
        "transforms/objects/box.py": "from ncore_convert.transforms.camera import view\n",
        "transforms/camera/__init__.py": "",
        "transforms/camera/view.py": "x = [min(a, b) for a in (0, 1)]\ny = max(a, c)\n",
        "transforms/noise.py": "from ncore_convert.transforms.camera.view import x\n",
        # a second camera view, a lidar stored by hand, a counter of its own, a pose read directly
        "converters/ds/__init__.py": "",
        "converters/ds/colour.py": "v = CameraView(cam, t, T, pinhole)\nf = ColourFrame(cam, t, T, p, load_rgb=g)\n",
        "converters/ds/labels.py": (
            "v = CameraView(cam, t, T, pinhole)\nlidar.store_frame(rays, meta, model_element=m)\n"
            "class Counts(Tally):\n    frames: int = 0\n"
        ),
        "validate/look.py": "T = loader.pose_graph.evaluate_poses('rig', 'world', t)\n",
        # state in a reader module: a lock, a counter changed by functions, a pool rebound, the environment
        "sources/state.py": (
            "import os, threading\n_lock = threading.Lock()\nSEEN = set()\nCOUNTS = {}\n_pool = None\nLIMIT = 3\n"
            "def f(x):\n    global _pool\n    SEEN.add(x)\n    COUNTS[x] = 1\n    os.environ['A'] = '1'\n"
            "    return LIMIT\n"
        ),
        "run/go.py": "from ncore_convert.sources import reader\n",
    }
    for rel, text in files.items():
        (pkg / rel).parent.mkdir(parents=True, exist_ok=True)
        (pkg / rel).write_text(text)
    graph, trees = import_graph(pkg)
    assert sorted(cycles(graph)) == [
        ["ncore_convert.converters.a", "ncore_convert.converters.b"],
        ["ncore_convert.sources.reader", "ncore_convert.transforms.geo"],
    ]
    assert layer_violations(graph, "ncore_convert") == [
        "ncore_convert.transforms.geo imports ncore_convert.sources.reader",
        "ncore_convert.run.go imports ncore_convert.sources.reader",
        "ncore_convert.validate.check imports ncore_convert.converters.a",
        "ncore_convert.views.look imports ncore_convert.converters.b",
        "ncore_convert.converters.c imports ncore_convert.views.look",
    ]
    assert module_state(trees, "ncore_convert.sources") == {
        "ncore_convert.sources.state": {
            "_lock: a module-level Lock",
            "SEEN: changed by a function",
            "COUNTS: changed by a function",
            "_pool: rebound by a function (global)",
            "os.environ: written",
        }
    }
    assert ncore_writer_users(trees) == {"ncore_convert.converters.b"}
    assert loader_constructors(trees) == {"ncore_convert.validate.check"}
    assert av2_transform_names(trees) == {"ncore_convert.transforms.geo": {"city_SE3_ego"}}
    assert torch_importers(trees) == {"ncore_convert.converters.c"}
    assert one_site_per_converter(calls_to(trees, "CameraView")) == {"ds": 2}
    assert set(calls_to(trees, "ColourFrame")) == {"ncore_convert.converters.ds.colour"}
    assert set(calls_to(trees, "store_frame", "model_element")) == {"ncore_convert.converters.ds.labels"}
    assert counter_classes(trees) == {"ncore_convert.converters.ds.labels"}
    assert set(calls_to(trees, "evaluate_poses")) == {"ncore_convert.validate.look"}
    assert own_box_geometry(trees) == {
        "ncore_convert.converters.slab": {"slab test at line 3"},
        "ncore_convert.validate.corners": {"corner table at line 1", "corner table at line 2"},
    }
    assert sorted(transform_layer_violations(graph, "ncore_convert")) == [
        "ncore_convert.transforms.noise imports ncore_convert.transforms.camera.view",
        "ncore_convert.transforms.objects.box imports ncore_convert.transforms.camera.view",
    ]
    assert loose_transforms(pkg) == ["geo", "noise"]
    (pkg / "converters" / "long.py").write_text("x = 1\n" * (MAX_MODULE_LINES + 1))
    (pkg / "converters" / "at_limit.py").write_text("x = 1\n" * MAX_MODULE_LINES)
    assert oversized_modules(pkg) == {"ncore_convert.converters.long": MAX_MODULE_LINES + 1}
    assert own_geometry(trees, ("ncore_convert.converters",)) == {
        "ncore_convert.converters.d": {"projection at line 1", "box test at line 2", "box test at line 3"}
    }
