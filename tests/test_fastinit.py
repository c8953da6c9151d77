"""fast_frozen: the cheaper constructor builds the same objects as the dataclass's own, stays
frozen, and refuses classes whose construction does more than store arguments."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import pytest

from companion.core import state
from companion.core.fastinit import fast_frozen
from companion.drivers import gps_solution, imu_protocol, servo_protocol
from companion.sim import truth

FAST_CLASSES = [
    state.ImuSample, state.ImuSlowSample, state.GpsFix, state.ServoState, state.EstimatorState,
    state.ControlOutput, state.HorizonMeasurement, truth.TruthState, imu_protocol.ImuFast,
    imu_protocol.ImuSlow, servo_protocol.ServoCommand, servo_protocol.PilotFrame,
    gps_solution.GpsSolution,
]


def _reference_init(cls: type) -> type:
    """The same fields and defaults through the dataclass's own generated constructor."""
    spec = [(f.name, f.type, f.default) for f in dataclasses.fields(cls)]
    return dataclasses.make_dataclass(
        "Ref" + cls.__name__,
        [(n, t) if d is dataclasses.MISSING else (n, t, d) for n, t, d in spec],
        frozen=True)


def _values(obj: object) -> tuple[object, ...]:
    return tuple(getattr(obj, f.name) for f in dataclasses.fields(obj))  # type: ignore[arg-type]


@pytest.mark.parametrize("cls", FAST_CLASSES, ids=lambda c: c.__name__)
def test_runtime_classes_build_what_the_dataclass_builds(cls: type) -> None:
    assert cls.__init__.__code__.co_filename.startswith("<fast_frozen")  # the fast path is on
    fields = dataclasses.fields(cls)
    ref = _reference_init(cls)
    # positional, every field given: distinct values so a swapped field would show
    values = [object() for _ in fields]
    fast = cls(*values)
    slow = ref(*values)
    assert _values(fast) == _values(slow)
    for f, v in zip(fields, values, strict=True):
        assert getattr(fast, f.name) is v
    # keywords, only the required ones: the defaults are the dataclass's
    required = {f.name: i for i, f in enumerate(fields) if f.default is dataclasses.MISSING}
    fast = cls(**required)
    slow = ref(**required)
    assert _values(fast) == _values(slow)
    with pytest.raises(dataclasses.FrozenInstanceError):
        setattr(fast, fields[0].name, 1)
    assert dataclasses.replace(fast, **{fields[0].name: -1}) == cls(**{**required,
                                                                       fields[0].name: -1})
    if required:
        with pytest.raises(TypeError):
            cls()  # a missing required field is refused as before


def test_equality_hash_and_repr_are_the_dataclasses() -> None:
    a = state.ImuSample(1, 2, (0.1, 0.2, 0.3), (0.0, 0.0, -9.8))
    b = state.ImuSample(t_ns=1, counter=2, rates_rad_s=(0.1, 0.2, 0.3),
                        accel_m_s2=(0.0, 0.0, -9.8), gyro_ok=True, accel_ok=True)
    assert a == b and hash(a) == hash(b)
    assert a != dataclasses.replace(b, accel_ok=False)
    assert repr(a).startswith("ImuSample(t_ns=1, counter=2, ")
    assert state.ImuSample.__init__.__qualname__ == "ImuSample.__init__"


def test_slotted_class_is_supported() -> None:
    @fast_frozen
    @dataclass(frozen=True, slots=True)
    class P:
        x: float
        y: float = 2.0

    p = P(1.0)
    assert (p.x, p.y) == (1.0, 2.0)
    assert not hasattr(p, "__dict__")
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.x = 3.0  # type: ignore[misc]


def test_refuses_what_it_cannot_build() -> None:
    @dataclass
    class Mutable:
        x: int

    with pytest.raises(TypeError, match="not a frozen dataclass"):
        fast_frozen(Mutable)

    @dataclass(frozen=True)
    class Factory:
        x: list[int] = field(default_factory=list)

    with pytest.raises(TypeError, match=r"Factory\.x"):
        fast_frozen(Factory)

    @dataclass(frozen=True)
    class Post:
        x: int

        def __post_init__(self) -> None:
            pass

    with pytest.raises(TypeError, match="__post_init__"):
        fast_frozen(Post)

    @dataclass(frozen=True)
    class NoInit:
        x: int = field(default=1, init=False)

    with pytest.raises(TypeError, match=r"NoInit\.x"):
        fast_frozen(NoInit)

    @dataclass(frozen=True, kw_only=True)
    class KwOnly:
        x: int

    with pytest.raises(TypeError, match=r"KwOnly\.x"):
        fast_frozen(KwOnly)
