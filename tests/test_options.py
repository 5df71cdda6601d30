"""The choices of algorithm as enums (lgvi_jax.options): members equal to their strings,
parsed and refused with the owner, the field and the valid values named, stored as members
by the modules whichever spelling built them."""

import dataclasses
import json
import pickle
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import pytest

import lgvi_jax as lj
from lgvi_jax import integrators
from lgvi_jax.options import (
    Adjoint,
    ChordMatrix,
    HamelMap,
    JacobianLoop,
    JacobianMode,
    LinearSolver,
    Variation,
)

ENUMS = {
    LinearSolver: ("unrolled", "lu"),
    Adjoint: ("implicit", "unrolled"),
    JacobianMode: ("auto", "forward", "reverse"),
    JacobianLoop: ("batched", "never", "always"),
    ChordMatrix: ("exact", "mass"),
    HamelMap: ("exp", "cayley"),
    Variation: ("paper", "exact"),
}


@pytest.mark.parametrize("enum", list(ENUMS), ids=lambda e: e.__name__)
def test_members_are_their_strings(enum):
    assert enum.values() == ENUMS[enum]
    for member in enum:
        value = member.value
        assert member == value and value == member
        assert hash(member) == hash(value)
        assert str(member) == value and f"{member}" == value and f"{member:>10}" == f"{value:>10}"
        assert {value: 1}[member] == 1 and {member: 2}[value] == 2
        assert json.dumps(member) == json.dumps(value)
        assert pickle.loads(pickle.dumps(member)) is member
        assert repr(member) == f"{enum.__name__}.{member.name}"


@pytest.mark.parametrize("enum", list(ENUMS), ids=lambda e: e.__name__)
def test_parse_accepts_members_and_strings(enum):
    for member in enum:
        assert enum.parse(member, "Owner", "field") is member
        assert enum.parse(member.value, "Owner", "field") is member
        assert enum.coerce(member.value) is member


@pytest.mark.parametrize("enum", list(ENUMS), ids=lambda e: e.__name__)
@pytest.mark.parametrize("bad", ["foo", "", "EXACT", 3, None])
def test_parse_refuses_a_bad_value_naming_owner_field_and_choices(enum, bad):
    with pytest.raises(ValueError) as err:
        enum.parse(bad, "Owner", "field")
    valid = ", ".join(repr(v) for v in ENUMS[enum])
    assert str(err.value) == f"Owner: field must be one of {valid}, got {bad!r}"
    assert enum.coerce(bad) is bad  # the converter leaves it to the owner's check


def test_a_member_of_another_choice_is_refused():
    # Equal strings, different concepts.
    assert ChordMatrix.EXACT == Variation.EXACT
    with pytest.raises(ValueError) as err:
        lj.LGVI(chord_matrix=Variation.EXACT)
    assert str(err.value) == ("LGVI: chord_matrix must be one of 'exact', 'mass', "
                              "got Variation.EXACT")
    with pytest.raises(ValueError, match="with_chord_matrix"):
        integrators.with_chord_matrix(lj.LGVI(), Variation.EXACT)


@pytest.mark.parametrize(
    "build, field, bad, message",
    [
        (lj.Newton, "linear_solver", "qr", "Newton: linear_solver must be one of 'unrolled', "
                                           "'lu', got 'qr'"),
        (lj.Newton, "adjoint", "foo", "Newton: adjoint must be one of 'implicit', "
                                      "'unrolled', got 'foo'"),
        (lj.Newton, "scalar_jacobian", "both", "Newton: scalar_jacobian must be one of "
                                               "'auto', 'forward', 'reverse', got 'both'"),
        (lj.Newton, "jacobian_loop", "sometimes", "Newton: jacobian_loop must be one of "
                                                  "'batched', 'never', 'always', got "
                                                  "'sometimes'"),
        (lj.LGVI, "chord_matrix", "jacobian", "LGVI: chord_matrix must be one of 'exact', "
                                              "'mass', got 'jacobian'"),
        (lj.HamelVI, "chord_matrix", "x", "HamelVI: chord_matrix must be one of 'exact', "
                                          "'mass', got 'x'"),
        (lj.HamelVI, "map", "quaternion", "HamelVI: map must be one of 'exp', 'cayley', "
                                          "got 'quaternion'"),
        (lj.HamelVI, "variation", "approximate", "HamelVI: variation must be one of 'paper', "
                                                 "'exact', got 'approximate'"),
    ],
)
def test_modules_refuse_a_bad_choice(build, field, bad, message):
    with pytest.raises(ValueError) as err:
        build(**{field: bad})
    assert str(err.value) == message
    with pytest.raises(ValueError) as err:  # also when replaced
        dataclasses.replace(build(), **{field: bad})
    assert str(err.value) == message


def test_defaults_are_members():
    newton = lj.Newton()
    assert newton.linear_solver is LinearSolver.UNROLLED
    assert newton.adjoint is Adjoint.IMPLICIT
    assert newton.scalar_jacobian is JacobianMode.AUTO
    assert newton.jacobian_loop is JacobianLoop.BATCHED
    assert lj.LGVI().chord_matrix is ChordMatrix.EXACT
    hamel = lj.HamelVI()
    assert hamel.map is HamelMap.EXP and hamel.variation is Variation.PAPER
    assert lj.LGVI.jacobian_mode is JacobianMode.REVERSE
    assert lj.HamelVI.jacobian_mode is JacobianMode.FORWARD
    for make in integrators.RIGID_METHODS.values():
        method = make()
        for name in ("chord_matrix", "map", "variation"):
            if hasattr(method, name):
                assert type(getattr(method, name)) in ENUMS, (method.name, name)


BUILDS = [
    (lambda c: lj.Newton(linear_solver=c), LinearSolver),
    (lambda c: lj.Newton(adjoint=c), Adjoint),
    (lambda c: lj.Newton(scalar_jacobian=c), JacobianMode),
    (lambda c: lj.Newton(jacobian_loop=c), JacobianLoop),
    (lambda c: lj.LGVI(chord_matrix=c), ChordMatrix),
    (lambda c: lj.HamelVI(chord_matrix=c), ChordMatrix),
    (lambda c: lj.HamelVI(map=c), HamelMap),
    (lambda c: lj.HamelVI(variation=c), Variation),
    (lambda c: lj.LGVI(newton=lj.Newton(adjoint=c, max_steps=4)), Adjoint),
]


@pytest.mark.parametrize("build, enum", BUILDS)
def test_built_from_a_string_or_a_member_is_the_same_module(build, enum):
    for member in enum:
        by_string, by_member = build(member.value), build(member)
        assert by_string == by_member and hash(by_string) == hash(by_member)
        leaves_s, def_s = jax.tree.flatten(by_string)
        leaves_m, def_m = jax.tree.flatten(by_member)
        assert def_s == def_m and str(def_s) == str(def_m)
        assert [type(v) for v in leaves_s] == [type(v) for v in leaves_m]
        # The stored field is the member.
        stored = [getattr(by_string, f.name) for f in dataclasses.fields(by_string)]
        nested = [getattr(v, f.name) for v in stored if isinstance(v, lj.Newton)
                  for f in dataclasses.fields(v)]
        assert any(v is member for v in stored + nested)
        assert not any(type(v) is str and v == member.value for v in stored + nested)


def test_one_jit_trace_for_a_string_and_a_member():
    traces = []

    @eqx.filter_jit
    def f(method, x):
        traces.append(method)
        return x + 1.0

    x = jnp.ones(3)
    f(lj.LGVI(chord_matrix="mass"), x)
    f(lj.LGVI(chord_matrix=ChordMatrix.MASS), x)
    f(lj.HamelVI(map="cayley", variation="exact"), x)
    f(lj.HamelVI(map=HamelMap.CAYLEY, variation=Variation.EXACT), x)
    f(lj.Newton(adjoint="unrolled", linear_solver="lu"), x)
    f(lj.Newton(adjoint=Adjoint.UNROLLED, linear_solver=LinearSolver.LU), x)
    assert len(traces) == 3
    f(lj.LGVI(), x)  # a different choice is a different program
    assert len(traces) == 4


def test_chord_matrix_helpers_take_strings_and_members():
    composed = integrators.resolve_method("lgvi@4", integrators.RIGID_METHODS)
    for chord in ("mass", ChordMatrix.MASS):
        method = integrators.with_chord_matrix(composed, chord)
        assert method.base.chord_matrix is ChordMatrix.MASS
        assert integrators.with_scalar_newton(method).base.newton.scalar is False
    from lgvi_jax.sweep import sweep_method

    for chord in ("mass", ChordMatrix.MASS):
        assert sweep_method("free-rigid-body", "lgvi", chord).chord_matrix is ChordMatrix.MASS
        assert (sweep_method("free-rigid-body", "lgvi", chord_matrix=chord)
                == sweep_method("free-rigid-body", "lgvi", "mass"))
    with pytest.raises(ValueError, match="chord_matrix must be one of 'exact', 'mass'"):
        integrators.with_chord_matrix(composed, "jacobian")


def test_exported():
    for enum in ENUMS:
        assert getattr(lj, enum.__name__) is enum and enum.__name__ in lj.__all__
    for enum in (ChordMatrix, HamelMap, Variation):
        assert getattr(integrators, enum.__name__) is enum


def test_newton_solution_names_its_iterations_newton_steps():
    sol = lj.newton_solve(lambda y, a: y**3 - a, jnp.array([1.0]), jnp.array(2.0))
    info = integrators.StepInfo.from_solution(sol)
    assert int(info.newton_steps) == int(sol.newton_steps) > 0
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert int(sol.num_steps) == int(sol.newton_steps)  # the deprecated name
    assert any(issubclass(w.category, DeprecationWarning) for w in caught)
