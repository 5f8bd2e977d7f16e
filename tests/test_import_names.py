"""Public API between packages: no module of calib/, drivers/, acquisition/ or sim_backend/ imports an
underscore name (a private function, class or module) from another of these packages, nor reaches one by
attribute access on an imported module (``pkg._name``)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("calib", "drivers", "acquisition", "sim_backend")


def _private(dotted: str) -> str | None:
    """The first underscore component of a dotted name (dunders such as __init__ are public), or None."""
    for part in dotted.split("."):
        if part.startswith("_") and not (part.startswith("__") and part.endswith("__")):
            return part
    return None


def cross_package_private_uses(path: Path, package: str) -> list[str]:
    """Underscore names of other packages that the module at ``path`` (in ``package``) imports or reaches."""
    tree = ast.parse(path.read_text(), filename=str(path))
    where = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path.name
    found, aliases = [], {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            top = node.module.split(".")[0]
            if top in PACKAGES and top != package:
                for a in node.names:
                    bad = _private(node.module) or _private(a.name)
                    if bad:
                        found.append(f"{where}:{node.lineno}: from {node.module} import {a.name}")
                    else:
                        aliases[a.asname or a.name] = f"{node.module}.{a.name}"
        elif isinstance(node, ast.Import):
            for a in node.names:
                top = a.name.split(".")[0]
                if top in PACKAGES and top != package:
                    if _private(a.name):
                        found.append(f"{where}:{node.lineno}: import {a.name}")
                    aliases[a.asname or top] = a.name
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and _private(node.attr):
            chain, v = [node.attr], node.value
            while isinstance(v, ast.Attribute):
                chain.append(v.attr)
                v = v.value
            if isinstance(v, ast.Name) and v.id in aliases:
                found.append(f"{where}:{node.lineno}: {v.id}.{'.'.join(reversed(chain))}")
    return found


def _modules():
    for pkg in PACKAGES:
        for p in sorted((ROOT / pkg).rglob("*.py")):
            yield pkg, p


def test_the_walker_sees_both_kinds_of_offence(tmp_path):
    src = tmp_path / "m.py"
    src.write_text("from calib.selfcal._solve import measurement_rows\nimport calib.diagnose as d\n"
                   "from calib.diagnose import pose_error\nfrom acquisition.x import _mine\n"
                   "x = d._hidden\ny = pose_error._z\n")
    found = cross_package_private_uses(src, "acquisition")
    assert len(found) == 3, found
    assert "_solve" in found[0] and "d._hidden" in found[1] and "pose_error._z" in found[2]


@pytest.mark.parametrize("package", PACKAGES)
def test_no_underscore_name_is_used_across_packages(package):
    offenders = [f for pkg, p in _modules() if pkg == package for f in cross_package_private_uses(p, pkg)]
    assert not offenders, "\n".join(offenders)
