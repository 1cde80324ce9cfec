"""Importing the module nerfstudio's entry points name does no work: no nerfstudio module, none of the plugin's
others (nerfstudio loads the dataparser entry points while its own data manager module is half imported, where
importing its trainer would close an import circle); the objects are built when an attribute is read."""

from __future__ import annotations

import ast
import subprocess
import sys

CHECK = """
import sys
before = set(sys.modules)
import kc_splatfacto.nerfstudio_plugin.entry_points as entry_points
loaded = sorted(m for m in set(sys.modules) - before
                if m.split('.')[0] in ('nerfstudio', 'torch', 'gsplat') or m.startswith('kc_splatfacto.'))
print(loaded)
"""


def test_importing_the_entry_point_module_imports_no_nerfstudio_and_builds_nothing():
    done = subprocess.run([sys.executable, "-c", CHECK], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    loaded = ast.literal_eval(done.stdout.strip().splitlines()[-1])
    assert loaded == ["kc_splatfacto.nerfstudio_plugin", "kc_splatfacto.nerfstudio_plugin.entry_points"]
