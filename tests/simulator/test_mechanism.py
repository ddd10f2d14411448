"""The simulated mechanism behind the emulated DAQ, and calibration from its wire data."""

import numpy as np
import pytest

from loopcal.calibration.errors import InputError
from loopcal.calibration.kinematics import euler_zyz, inverse_kinematics, lengths_to_volts
from loopcal.calibration.parameters import NOMINAL, PAPER7
from loopcal.calibration.pipeline import calibrate
from loopcal.calibration.poses import still_poses
from loopcal.calibration.simulate import perturbed_truth, reachable
from loopcal.drivers import open_daq
from loopcal.drivers.ldq412 import at_rail, code_to_volts
from loopcal.simulator import Emulator, ManualClock
from loopcal.simulator.mechanism import MechanismSource
from loopcal.simulator.scenarios import HandMoves, Static, Sweep, min_jerk, scenario_named


def test_hand_moves_are_deterministic_in_any_query_order():
    t = np.linspace(0, 120, 500)
    a = HandMoves(3).rotation(t)
    late_first = HandMoves(3)
    b = np.concatenate([late_first.rotation(t[250:]), late_first.rotation(t[:250])])
    b = np.concatenate([b[250:], b[:250]])
    assert np.array_equal(a, b)
    assert not np.allclose(a, HandMoves(4).rotation(t))


@pytest.mark.slow
def test_a_hand_streaming_for_hours_keeps_a_bounded_history_and_can_go_back():
    """The emulator asks for one scan at a time, forward, for months: what HandMoves keeps
    (and so each call's cost and its memory) stays bounded; an early time asked for after
    it was forgotten is drawn again from the seed, the same."""
    from loopcal.simulator import scenarios

    h, fresh = HandMoves(5, twist_every=2), HandMoves(5, twist_every=2)
    early = np.linspace(0.0, 30.0, 61)
    first = fresh.rotation(early)
    kept = []
    for t0 in np.arange(0.0, 3600.0, 60.0):  # an hour (six times the history), a minute a read
        h.rotation(t0 + np.arange(1200) / 20.0)
        kept.append(len(h._segments))
    horizon = (scenarios.HISTORY_S + 60.0) / 0.5 + scenarios.FORGET_BATCH  # moves >= 0.5 s
    assert max(kept) <= horizon and kept[-1] < kept[len(kept) // 2] + scenarios.FORGET_BATCH
    assert max(kept) < 3600.0 / 3.0  # far fewer than the moves and pauses of an hour
    late = h.rotation(np.array([3595.0]))
    assert np.array_equal(h.rotation(early), first)  # forgotten, drawn again: the same
    assert np.array_equal(h.rotation(np.array([3595.0])), late)


def _swivel_deg(R: np.ndarray) -> np.ndarray:
    a, _, g = euler_zyz(R).T
    return np.degrees(np.angle(np.exp(1j * (a + g))))


@pytest.mark.slow
def test_a_twisting_technician_twists_every_other_move_and_stays_in_the_workspace():
    truth = perturbed_truth(np.random.default_rng(2))
    plain, twisting = HandMoves(5, params=truth), HandMoves(5, params=truth, twist_every=2)
    t = np.linspace(0, 300, 6000)
    assert np.array_equal(plain.rotation(t), HandMoves(5, params=truth, twist_every=0).rotation(t))
    held = []
    for h in (plain, twisting):
        ends = [b for _, b, moving in h.segments_until(300) if moving]  # where each move ends
        held.append(np.abs(_swivel_deg(h.rotation(np.array(ends)))))
    # every second move ends at the most twisted of eight draws: far more twisted than the
    # uniform draws of the other moves and of the plain technician
    assert np.median(held[1][1::2]) > 1.5 * np.median(held[1][0::2])
    assert np.median(held[1][1::2]) > 1.5 * np.median(held[0])
    assert reachable(twisting.rotation(t), truth, margin_mm=9.0).all()
    with pytest.raises(InputError, match="twist_every"):
        HandMoves(5, twist_every=-1)
    # what loopcal simulate --twist-every serves
    served = scenario_named("hand", seed=5, params=truth, twist_every=2)
    assert np.array_equal(served.rotation(t), twisting.rotation(t))


def test_hand_moves_stay_in_the_workspace_and_pause():
    truth = perturbed_truth(np.random.default_rng(2))
    h = HandMoves(5, params=truth)
    t = np.linspace(0, 300, 3000)
    R = h.rotation(t)
    assert reachable(R, truth, margin_mm=9.0).all()
    segs = h.segments_until(300)
    pauses = [(a, b) for a, b, moving in segs if not moving]
    moves = [(a, b) for a, b, moving in segs if moving]
    assert len(pauses) > 20 and len(moves) > 20
    a, b = pauses[3]
    held = h.rotation(np.linspace(a, b - 1e-6, 20))
    assert np.abs(held - held[0]).max() == 0.0  # the plate is still during a pause


def test_moves_start_and_end_at_rest():
    assert min_jerk(np.array([0.0, 1.0])).tolist() == [0.0, 1.0]
    eps = 1e-4
    slope = (min_jerk(np.array([eps, 1.0])) - min_jerk(np.array([0.0, 1 - eps]))) / eps
    assert abs(slope[0]) < 1e-6 and abs(slope[1]) < 1e-6


def test_source_is_the_inverse_kinematics_of_the_truth():
    truth = perturbed_truth(np.random.default_rng(3))
    src = MechanismSource(Static((30.0, 20.0, -10.0)), truth, noise_volts=0.0)
    t = np.array([1.0, 1.00025, 1.0005, 1.00075])
    from loopcal.calibration.kinematics import from_euler_zyz

    R = from_euler_zyz(np.radians([30.0, 20.0, -10.0]))
    expected = lengths_to_volts(inverse_kinematics(R, truth), truth)[0]
    assert np.allclose(src.convert(t), expected, atol=1e-12)


def test_channel_skew_of_a_moving_plate():
    src = MechanismSource(Sweep(period_s=4.0), NOMINAL, noise_volts=0.0)
    t0 = 1.0
    skewed = src.convert(t0 + 250e-6 * np.arange(4))
    same_instant = src.clean(np.full(4, t0))
    # channel 1 is the scan's instant; channel 4 is converted 750 us later
    assert skewed[0] == same_instant[0]
    assert abs(skewed[3] - same_instant[3]) > 1e-4


def test_bad_sweep_or_noise_is_refused():
    with pytest.raises(ValueError, match="leaves the reachable workspace"):
        Sweep(tilt_deg=60.0)
    with pytest.raises(ValueError, match="noise"):
        MechanismSource(Static(), NOMINAL, noise_volts=-1.0)


@pytest.mark.slow
def test_calibration_from_wire_data_recovers_the_offsets():
    """Five minutes of a technician moving the plate, read over Modbus TCP, still stretches
    averaged, best 50 poses selected, paper's seven parameters identified."""
    truth = perturbed_truth(np.random.default_rng(1))
    src = MechanismSource(HandMoves(1, params=truth), truth, seed=1)
    clock = ManualClock()
    with Emulator("modbus-tcp", src, clock=clock) as emu:
        # not a timing test: an answer slowed by a busy machine must not end it
        daq = open_daq(emu.url, timeout=2.0)
        scans = []
        for _ in range(300):
            clock.advance(1.0)
            scans += daq.read_scans()
        daq.close()
        assert [s.counter for s in scans] == [s.counter for s in emu.truth]
    codes = np.array([s.codes for s in scans])
    poses = still_poses(code_to_volts(codes), valid=~at_rail(codes).any(axis=1))
    assert len(poses) >= 50
    res = calibrate(poses.volts, PAPER7, NOMINAL).identification
    assert res.problems() == []
    z = (res.params - truth)[16:20] / res.std[:4]
    assert np.all(np.abs(z) < 3), z
    assert np.all(res.std[:4] < 0.1)
    assert np.abs(res.params - truth)[16:20].max() < 0.2


def test_replay_reproduces_a_recording_bit_for_bit(tmp_path):
    from loopcal.drivers.ldq412 import code_to_volts as c2v
    from loopcal.simulator.mechanism import ReplaySource

    truth = perturbed_truth(np.random.default_rng(6))
    clock = ManualClock()
    with Emulator("modbus-tcp", MechanismSource(HandMoves(6), truth, seed=6), clock=clock) as a:
        clock.advance(30.0)
        recorded = a.truth
    times = np.array([s.t_s for s in recorded])
    codes = np.array([s.codes for s in recorded])
    clock2 = ManualClock()
    with Emulator("modbus-tcp", ReplaySource(times, c2v(codes)), clock=clock2) as b:
        clock2.advance(30.0)
        replayed = b.truth
    assert [s.codes for s in replayed] == [s.codes for s in recorded]
    with pytest.raises(ValueError, match="increase"):
        ReplaySource(np.array([0.0, 0.0]), np.zeros((2, 4)))
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"type": "header"}\nnot json\n')
    with pytest.raises(ValueError, match="bad.jsonl:2: not JSON"):
        ReplaySource.from_truth_file(bad)


def test_same_scenario_and_seed_give_the_same_codes_pinned():
    """The simulated mechanism is bit-exact: the codes of 20 s of hand moves (seed 0) are
    pinned by their hash, so a change of numbers anywhere on the way (kinematics, scenario,
    noise stream, converter) shows up here. The wire format itself is pinned by the golden
    frames of the emulator tests."""
    import hashlib

    truth = perturbed_truth(np.random.default_rng(0))
    clock = ManualClock()
    src = MechanismSource(HandMoves(0, params=truth), truth, seed=0)
    with Emulator("modbus-tcp", src, clock=clock) as emu:
        clock.advance(20.0)
        codes = np.array([s.codes for s in emu.truth], dtype=np.uint16)
    assert len(codes) == 401
    digest = hashlib.sha256(codes.tobytes()).hexdigest()
    assert digest == "f0f15aea9051e87ed2c7fefd8ff489400425c1c6e70969999129e0cb71692097"
