"""systems.load_system: built-in names, importable ``module:function`` and ``file.py:function`` specs."""

import sys
import textwrap

import pytest

import torchmisspec as tms
from torchmisspec.systems import load_system

USER_MODULE = """
import torch
import torchmisspec as tms

def damped():
    A = torch.tensor([[0.0, 1.0], [-1.0, -0.1]], dtype=torch.float64)
    return tms.MisspecifiedSystem(tms.systems.LinearField(A), 2, name="damped")

def broken():
    raise RuntimeError("no parameters file\\nsecond line")

def not_a_system():
    return {"state_dim": 2}

NUMBER = 3

SYSTEM = damped()
"""


@pytest.fixture
def user_module(tmp_path, monkeypatch):
    name = f"tms_user_systems_{tmp_path.name.replace('-', '_')}"
    (tmp_path / f"{name}.py").write_text(textwrap.dedent(USER_MODULE), encoding="utf-8")
    (tmp_path / "bad_syntax_mod.py").write_text("def f(:\n", encoding="utf-8")
    monkeypatch.syspath_prepend(str(tmp_path))
    yield name
    sys.modules.pop(name, None)
    sys.modules.pop("bad_syntax_mod", None)


def test_builtin_names_and_systems_pass_through():
    assert load_system("paper_linear").name == "paper_linear"
    system = tms.systems.paper_gravity()
    assert load_system(system) is system


def test_module_function_spec(user_module):
    system = load_system(f"{user_module}:damped")
    assert isinstance(system, tms.MisspecifiedSystem) and system.name == "damped" and system.state_dim == 2


def test_a_module_level_system_is_taken_as_it_is(user_module):
    """A newcomer's system file builds the system at the top level (``system = MisspecifiedSystem(...)``): naming it
    was refused as 'expected a function'."""
    system = load_system(f"{user_module}:SYSTEM")
    assert isinstance(system, tms.MisspecifiedSystem) and system.name == "damped"


def test_file_path_spec(tmp_path, user_module):
    system = load_system(f"{tmp_path / user_module}.py:damped")
    assert system.name == "damped"


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("nope", r"unknown system name 'nope': expected one of \['paper_gravity', 'paper_linear'\] or "
         r"'module:function'"),
        ("no_such_module_xyz:f", r"expected an importable module 'no_such_module_xyz', got "
         r"ModuleNotFoundError: No module named 'no_such_module_xyz' when importing it"),
        ("bad_syntax_mod:f", r"got SyntaxError.* when importing it"),
        ("{mod}:missing", r"expected a function 'missing' in module '{mod}', got none "
         r"\(the module defines \[.*'damped'"),
        ("{mod}:NUMBER", r"expected 'NUMBER' to be a function, got int"),
        ("{mod}:broken", r"expected broken\(\) to return a MisspecifiedSystem, got RuntimeError: no parameters file "
         r"second line when calling it \(at .*{mod}.py:10, in broken\)$"),
        ("{mod}:not_a_system", r"expected not_a_system\(\) to return a torchmisspec MisspecifiedSystem, got dict"),
        ("{mod}:", r"expected 'module:function' with a function name after the colon"),
        ("does/not/exist.py:f", r"expected an existing Python file, got 'does/not/exist.py'"),
    ],
)  # fmt: skip
def test_bad_specs_are_input_errors(user_module, spec, message):
    spec = spec.format(mod=user_module)
    with pytest.raises(tms.InputError, match=message.format(mod=user_module)):
        load_system(spec)


def test_non_string_spec():
    with pytest.raises(tms.InputError, match="expected a name or 'module:function', got int"):
        load_system(3)
