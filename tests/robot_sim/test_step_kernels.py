"""The allocation-free control step computes what Pinocchio's and MuJoCo's
allocating functions compute: frame Jacobians, log3, the operational-space
inertia, the hand's joint torques, and the whole impedance law."""

import mujoco
import numpy as np
import pinocchio as pin
import pytest

from robot_sim.arm.kinematics import ArmKinematics, FRAMES, READY
from robot_sim.krc.law import ImpedanceCommand, KrcController, SafetyReason, pose_to_cart_pos
from robot_sim.krc.law_arithmetic import frame_jacobian, lambda_diagonal, log3
from robot_sim.arm.description import LWR4
from robot_sim.world.physics import Simulation
from robot_sim.world.tasks import Valley, free_space, valley

LOCAL, LWA = pin.ReferenceFrame.LOCAL, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED


def random_states(n, seed=0):
    rng = np.random.default_rng(seed)
    for q in rng.uniform(0.95 * np.array(LWR4.q_min), 0.95 * np.array(LWR4.q_max), size=(n, 7)):
        yield q, rng.normal(size=7)


@pytest.fixture(scope="module")
def kin():
    return ArmKinematics()


def test_frame_jacobians_from_the_joint_jacobians_are_pinocchios(kin):
    out = np.empty((6, 7))
    for q, qd in random_states(100):
        kin.update_dynamics(q, qd)
        for frame in FRAMES:
            rotation, translation = kin.frame_views(frame)
            for reference, local in ((LOCAL, True), (LWA, False)):
                frame_jacobian(kin.views["J"], rotation, translation, kin.support(frame), local, out)
                expected = pin.getFrameJacobian(kin.model, kin.data, kin.frame_ids[frame], reference)
                np.testing.assert_allclose(out, expected, rtol=0, atol=1e-12)


def test_views_follow_the_updates(kin):
    J, nle = kin.views["J"], kin.views["nle"]
    rotation, translation = kin.frame_views("tcp")
    for q, qd in random_states(5, seed=1):
        kin.update_dynamics(q, qd)
        np.testing.assert_array_equal(J, pin.computeJointJacobians(kin.model, kin.model.createData(), q))
        np.testing.assert_allclose(nle, pin.nonLinearEffects(kin.model, kin.model.createData(), q, qd), atol=1e-12)
        oMtcp = kin.forward(q)
        np.testing.assert_allclose(rotation, oMtcp.rotation, atol=1e-15)
        np.testing.assert_allclose(translation, oMtcp.translation, atol=1e-15)


def test_log3_is_pinocchios():
    rng = np.random.default_rng(2)
    rotations = [pin.exp3(rng.normal(size=3)) for _ in range(500)]
    for angle in (0.0, 1e-9, 1e-6, 1e-3, 1.0, np.pi - 1e-3, np.pi - 1e-5, np.pi - 1e-7, np.pi):
        for _ in range(30):
            axis = rng.normal(size=3)
            rotations.append(pin.exp3(angle * axis / np.linalg.norm(axis)))
    work, out = np.empty((4, 3)), np.empty(3)
    for R in rotations:
        # commanded rotations are orthonormal only to FRI's tolerance: log3 renormalises
        for M in (R, R + rng.normal(size=(3, 3)) * 1e-7):
            log3(M, work, out)
            np.testing.assert_allclose(out, pin.log3(M), rtol=0, atol=1e-10)


def test_lambda_diagonal_is_the_cartesian_mass_in_tcp_axes(kin):
    J = np.empty((6, 7))
    L, X, A, La = np.empty((7, 7)), np.empty((7, 6)), np.empty((6, 6)), np.empty((6, 6))
    y, out = np.empty(6), np.empty(6)
    for q, qd in random_states(50, seed=3):
        kin.update_dynamics(q, qd)
        rotation, translation = kin.frame_views("tcp")
        frame_jacobian(kin.views["J"], rotation, translation, kin.support("tcp"), True, J)
        lambda_diagonal(kin.views["M"], J, L, X, A, La, y, out)
        R = kin.placement("tcp").rotation
        Rb = np.zeros((6, 6))
        Rb[:3, :3] = Rb[3:, 3:] = R
        expected = np.maximum(np.diag(Rb.T @ kin.cartesian_mass(q, "tcp") @ Rb), 1e-3)
        np.testing.assert_allclose(out, expected, rtol=1e-9)


@pytest.mark.parametrize("world", [free_space(), valley(Valley())], ids=["free_space", "valley"])
def test_apply_is_mj_applyFT_plus_the_drive_torques(world):
    sim = Simulation(world)
    rng = np.random.default_rng(4)
    for q, qd in random_states(30, seed=5):
        sim.reset(q, qd)
        hand, tau = rng.normal(size=6) * 10.0, rng.normal(size=7) * 5.0
        sim.apply(tau, hand)
        expected = np.zeros(sim.model.nv)
        mujoco.mj_applyFT(sim.model, sim.data, hand[:3], hand[3:], sim.data.site_xpos[sim._flange_site],
                          sim._flange_body, expected)
        np.testing.assert_allclose(sim.external_joint_torques() - sim.data.qfrc_constraint[sim._dof],
                                   expected[sim._dof], atol=1e-12)
        # the kernel's reading is the numpy expressions', bit for bit
        wrench, torques = np.empty(6), np.empty(7)
        sim.sense(wrench, torques)
        assert np.array_equal(torques, sim.data.qfrc_constraint[sim._dof] + sim._hand_qfrc[sim._dof])
        ft = np.concatenate([sim.data.sensordata[sim._force_adr:sim._force_adr + 3],
                             sim.data.sensordata[sim._torque_adr:sim._torque_adr + 3]])
        assert np.array_equal(wrench, -ft) and np.array_equal(sim.sensor_wrench(), -ft)
    with pytest.raises(ValueError, match=r"wrench \(6,\) and torques \(7,\), got \(6,\) and \(6,\)"):
        sim.sense(np.empty(6), np.empty(6))  # the kernel writes by address: a short buffer is refused first
        expected[sim._dof] += tau
        np.testing.assert_allclose(sim.data.qfrc_applied, expected, atol=1e-12)
        sim.apply(tau)
        np.testing.assert_array_equal(sim.data.qfrc_applied[sim._dof], tau)


def reference_impedance(kin, q, qd, command):
    """Eq. 79 with Pinocchio's allocating functions, as the law was first written."""
    kin.update(q, qd)
    nle = kin.nonlinear_effects(q, qd)
    oMtcp = kin.placement("tcp")
    J = kin.jacobian("tcp", LOCAL)
    m = command.cart_pos.reshape(3, 4)
    error = np.concatenate([oMtcp.rotation.T @ (m[:, 3] - oMtcp.translation), pin.log3(oMtcp.rotation.T @ m[:, :3])])
    Rb = np.zeros((6, 6))
    Rb[:3, :3] = Rb[3:, 3:] = oMtcp.rotation
    lam = np.maximum(np.diag(Rb.T @ kin.cartesian_mass(q, "tcp") @ Rb), 1e-3)
    k = command.cart_stiffness
    F = k * error - 2.0 * command.cart_damping * np.sqrt(k * lam) * (J @ qd) + command.add_tcp_ft
    return J.T @ F + nle, F


def test_the_impedance_law_is_eq_79(kin):
    rng = np.random.default_rng(6)
    for q, qd in random_states(30, seed=7):
        krc = KrcController(kin)  # a fresh controller refreshes Lambda on its first cycle
        target = pin.SE3(pin.exp3(rng.normal(size=3) * 0.3) @ kin.forward(q).rotation,
                         kin.forward(q).translation + rng.normal(size=3) * 0.05)
        command = ImpedanceCommand(pose_to_cart_pos(target), rng.uniform(0.0, [3000.0] * 3 + [200.0] * 3),
                                   rng.uniform(0.0, 1.0, 6), rng.normal(size=6))
        tau = krc.compute(q, qd, command, hold=False).copy()
        assert krc.safety == SafetyReason.NONE
        expected, wrench = reference_impedance(kin, q, qd, command)
        np.testing.assert_allclose(krc.last_wrench_tcp, wrench, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(tau, np.clip(expected, -krc.tau_max, krc.tau_max), rtol=1e-9, atol=1e-9)
        np.testing.assert_array_equal(krc.last_tau, tau)


def test_compute_returns_its_buffer_and_the_cell_copies_it(kin):
    krc = KrcController(kin)
    first = krc.compute(READY, np.zeros(7))
    assert krc.compute(READY, np.zeros(7)) is first  # documented: copy to keep


def test_what_holds_its_buffers_addresses_refuses_to_be_copied():
    """A copy would keep the original's addresses: its kernels would write the original's
    memory (or freed memory).  Copying, deep-copying and pickling each say so instead."""
    import copy
    import pickle

    from robot_sim.ati.sensor import AtiConfig, AtiSensor
    from robot_sim.cell import RobotCell

    cell = RobotCell(valley())
    for thing in (cell, cell.sim, cell.krc, cell.ati, AtiSensor(AtiConfig.mini45(), 1)):
        for how in (copy.copy, copy.deepcopy, pickle.dumps):
            with pytest.raises(TypeError, match=f"{type(thing).__name__} holds the addresses of its own buffers"):
                how(thing)


def _tip_contact_states(world, centre, spread, n, seed):
    """Simulations with the tool tip placed (by IK, then mj_forward) at random points
    around ``centre``: those where it touches something."""
    from robot_sim.cell import RobotCell

    cell = RobotCell(world, seed=0, with_sensor=False)
    rng = np.random.default_rng(seed)
    down = np.diag([1.0, -1.0, -1.0])
    for _ in range(n):
        try:
            cell.place_tcp(np.asarray(centre) + rng.uniform(-1.0, 1.0, 3) * spread, down)
        except ValueError:  # out of reach with the tool pointing down
            continue
        if cell.sim.data.ncon:
            yield cell.sim


def test_the_contact_kernel_reads_what_the_python_loop_reads():
    """``Simulation.contacts`` (one kernel over MuJoCo's contact array, mj_contactForce and
    numpy's dgemv by address) gives ``contacts_numpy``'s bits: in the valley (the tip
    between two plates), in the coupler (the floor and the walls), and on a plane, where
    MuJoCo orders the tip second in the contact (the plates and the coupler order it
    first: the force's sign flips)."""
    from robot_sim.world import physics
    from robot_sim.world.tasks import Surface, WorldSpec, hose_coupler

    if physics._tip_contacts is None:
        pytest.skip(f"no contact kernel here: {physics.WHY_NO_CONTACT_KERNEL}")
    plane = free_space()
    plane = WorldSpec("plane", plane.xml.replace(
        "<worldbody>", '<worldbody>\n    <geom name="table" type="plane" pos="0.55 0 0.2" size="0.3 0.3 0.01" '
        'contype="0" conaffinity="0"/>', 1).replace(
        "  <sensor>", '  <contact><pair geom1="tool_tip" geom2="table"/></contact>\n  <sensor>', 1),
        None, {"table": Surface("plate", 0.25, 0.005)})
    seen = {"tip first": 0, "tip second": 0, "two or more on the tip": 0}
    for world, centre, spread in ((valley(), (0.55, 0.0, 0.20), (0.2, 0.05, 0.02)),
                                  (hose_coupler(), (0.55, 0.0, 0.20), (0.03, 0.03, 0.02)),
                                  (plane, (0.55, 0.0, 0.20), (0.1, 0.1, 0.005))):
        states = 0
        for sim in _tip_contact_states(world, centre, spread, 60, seed=len(world.name)):
            contact, tip = sim.data.contact, sim._tip_geom
            firsts, seconds = int(np.sum(contact.geom1 == tip)), int(np.sum(contact.geom2 == tip))
            seen["tip first"] += firsts
            seen["tip second"] += seconds
            seen["two or more on the tip"] += firsts + seconds >= 2
            force, roles, names = sim.contacts()
            expected_force, expected_roles, expected_names = sim.contacts_numpy()
            assert force.tobytes() == expected_force.tobytes(), (world.name, force, expected_force)
            assert (roles, names) == (expected_roles, expected_names)
            # the cell's call (no roles), twice: the second takes the names made by the first
            for _ in range(2):
                force, names = sim.tip_contacts()
                assert force.tobytes() == expected_force.tobytes() and names == expected_names
                names.append("not a geom")  # what a caller does with its list stays its own
            states += 1
        assert states >= 10, f"{world.name}: the tip touched something in {states} of 60 placements"
    assert all(seen.values()), seen


def test_update_with_jacobian_leaves_what_the_bindings_leave(kin):
    """One call to the extension (forwardKinematics, computeJointJacobians,
    updateFramePlacements, getFrameJacobian LOCAL into a buffer) against the four calls
    through Pinocchio's bindings, on another Data: the same bits, in the Jacobian and in
    every frame placement and joint Jacobian it leaves."""
    from robot_sim.arm import kinematics

    if kinematics._MEASURED_KINEMATICS is None:
        pytest.skip(f"no extension here: {kinematics.PINOCCHIO_INPLACE_MISSING or 'an older build'}")
    reference = kin.model.createData()
    out = np.full((6, 7), np.nan)
    for q, _ in random_states(200, seed=3):
        for frame in FRAMES:
            kin.update_with_jacobian(q, frame, out)
            pin.forwardKinematics(kin.model, reference, q)
            pin.computeJointJacobians(kin.model, reference, q)
            pin.updateFramePlacements(kin.model, reference)
            expected = pin.getFrameJacobian(kin.model, reference, kin.frame_ids[frame], LOCAL)
            assert out.tobytes() == expected.tobytes(), frame
            assert kin.data.J.tobytes() == reference.J.tobytes()
            for mine, theirs in zip(kin.data.oMf, reference.oMf):
                assert mine.homogeneous.tobytes() == theirs.homogeneous.tobytes()


def test_pinocchio_called_from_a_kernel_leaves_what_the_extension_leaves(kin):
    """The extension's C functions, called by address from a numba kernel (as the cell's
    physics cycle calls them), leave the bits its Python functions leave; and a bad
    argument comes back as a failure code, not an exception through C."""
    from numba import njit

    from robot_sim.arm import kinematics as k

    if not k.COMPUTE_ALL_TERMS:
        pytest.skip(f"no extension here: {k.PINOCCHIO_INPLACE_MISSING or 'an older build'}")

    @njit
    def dynamics(fn, model, data, q, v):
        return k.call_compute_all_terms(fn, model, data, q, v)

    @njit
    def measured(fn, model, data, q, frame, jacobian):
        return k.call_measured_kinematics(fn, model, data, q, frame, jacobian)

    other = ArmKinematics()
    expected, got = np.empty((6, 7)), np.full((6, 7), np.nan)
    for q, qd in random_states(100, seed=5):
        kin.update_dynamics(q, qd)
        assert dynamics(k.COMPUTE_ALL_TERMS, *other.native, q.ctypes.data, qd.ctypes.data) == 0
        for name in ("J", "M", "nle"):
            assert other.views[name].tobytes() == kin.views[name].tobytes(), name
        for mine, theirs in zip(other.data.oMf, kin.data.oMf):
            assert mine.homogeneous.tobytes() == theirs.homogeneous.tobytes()
        kin.update_with_jacobian(q, "tcp", expected)
        assert measured(k.MEASURED_KINEMATICS, *other.native, q.ctypes.data, kin.frame_ids["tcp"],
                        got.ctypes.data) == 0
        assert got.tobytes() == expected.tobytes()
    q = READY.copy()
    assert measured(k.MEASURED_KINEMATICS, *other.native, q.ctypes.data, 10**6, got.ctypes.data) != 0


@pytest.mark.parametrize("substeps", [1, 2])
def test_the_compiled_cycle_measures_and_steps_as_the_python_calls(substeps):
    """``RobotCell.begin_cycle`` through ``_measure_at`` (the joint noise, Pinocchio at the
    true and the measured joints, the true twist, the external wrench estimate) and
    ``end_cycle`` through ``_physics_cycle_at`` (the law, the torques applied, MuJoCo's
    step by address, per physics step) against their Python calls, cell beside cell from
    the same state: gravity compensation with a hand
    pushing, then Cartesian impedance pressing the tool onto a plate, then holds; the same
    measurement, true pose and twist, joint state, torques and sensed wrench, bit for bit,
    every cycle."""
    from robot_sim.cell import RobotCell
    from robot_sim.krc.packets import CommandPacket
    from robot_sim.world.tasks import physics_step
    from robot_sim.world.teacher import DOWN

    world = valley(Valley(), timestep=physics_step(substeps))
    cells = [RobotCell(world, seed=1) for _ in range(2)]
    if cells[0]._compiled is None:
        pytest.skip("no compiled cycle here (MuJoCo's, numpy's BLAS or the extension's C functions are missing)")
    cells[1]._compiled = None  # the Python calls
    start = np.array([0.6, -0.08, 0.26])
    for cell in cells:
        cell.place_tcp(start, DOWN)
        cell.start()
    target = np.hstack([DOWN, (start - [0.0, 0.0, 0.06])[:, None]]).ravel()
    hand = np.array([0.0, 8.0, -20.0, 0.0, 0.0, 0.0])
    stepped, pressed = 0, 0.0
    for k in range(1400):
        results = []
        measured = []
        for cell in cells:
            cell.krc.gravity_compensation = k < 300
            if k == 0:
                cell.fri.request_command_mode()  # entered once the link has been PERFECT for 500 cycles
            m = cell.begin_cycle()
            measured.append(np.concatenate([m.msr_jnt_pos, m.msr_cart_pos, m.est_ext_tcp_ft, cell.true_tcp_pose,
                                            cell.true_tcp_twist]))
            if k < 1000 or k % 7:  # then now and then a missed answer: the link bridges, or holds
                cell.receive(CommandPacket(m.seq, target, np.array([2000.0] * 3 + [150.0] * 3), np.full(6, 0.7)),
                             m.stamp_ns + 100_000)
            results.append(cell.end_cycle(hand if k < 300 else None))
        a, b = cells
        assert measured[0].tobytes() == measured[1].tobytes(), k
        assert a.sim.data.qpos.tobytes() == b.sim.data.qpos.tobytes(), k
        assert a.sim.data.qvel.tobytes() == b.sim.data.qvel.tobytes(), k
        assert results[0].tau.tobytes() == results[1].tau.tobytes(), k
        assert a.tool_wrench.tobytes() == b.tool_wrench.tobytes(), k
        assert a.krc.safety == b.krc.safety
        stepped += a.fri.state == 2
        pressed = max(pressed, float(np.linalg.norm(a.contact_force)))
    assert stepped > 300, "the link never reached command mode: the impedance law was not compared"
    assert pressed > 1.0, f"the tool never pressed on the plate (at most {pressed:.2f} N)"


def test_the_valley_teachers_compiled_step_is_its_python_step():
    """``ValleyTeacher.step`` through ``_valley_step_at`` (the script, the path noise, the
    hand's impedance and tremor in one call; numpy's ddot and dgemm and Pinocchio's log3 by
    address) against its Python step, teacher beside teacher from the same seed, on both
    sides of the valley, through all three phases: the same wrench bit for bit, the same
    phase and the same end; the tool's rotation comes as a view into its 3x4 pose, as the
    teacher node passes it."""
    import robot_sim.world.teacher as teacher_module
    from robot_sim.world.teacher import DOWN, ValleyTeacher

    rng = np.random.default_rng(5)
    for side in (-1, 1):
        start = np.array([0.62, side * 0.08, 0.30])
        compiled, python = (ValleyTeacher(Valley(), start, 0.5, np.random.default_rng(3)) for _ in range(2))
        if compiled._compiled is None:
            pytest.skip(f"no compiled step here (LOG3 {teacher_module.LOG3}, BLAS {teacher_module.blas.WHY})")
        python._compiled = None
        x, phases = start.copy(), set()
        for k in range(4000):
            pose = np.asarray(np.hstack([pin.exp3(rng.normal(size=3) * 0.1) @ DOWN, x[:, None]]).ravel().tolist())
            pose = pose.reshape(3, 4)
            v, w = rng.normal(size=3) * 0.05, rng.normal(size=3) * 0.1
            force = np.asarray((rng.normal(size=3) * (3.0 if k > 500 else 0.0)).tolist())
            touching = [("plate_left" if side < 0 else "plate_right")] if k > 500 else []
            got = compiled.step(0.001, pose[:, 3], v, pose[:, :3], w, force, touching)
            expected = python.step(0.001, pose[:, 3], v, pose[:, :3], w, force, touching)
            assert got.tobytes() == expected.tobytes(), (side, k)
            assert (compiled.phase, compiled.done) == (python.phase, python.done), (side, k)
            phases.add(compiled.phase)
            x += [-1e-4, -side * 2e-5, -5e-5]
        assert phases == {0, 1, 2} and compiled.done


def test_a_cycle_closed_from_the_links_slot_is_the_cycle_end_cycle_closes():
    """The robot node's way through a cycle, the command's numbers straight into the FRI
    link (``receive_fields``) and the cycle closed from its slot (``RobotCell.close``),
    against the packet's way (``receive``, ``end_cycle``), cell beside cell: a hand
    pushing, then impedance onto a plate, answers missed now and then (bridged, held) and
    some refused (a stiffness out of range): the same outcome, joint state and sensed
    wrench, bit for bit, every cycle."""
    from robot_sim.cell import RobotCell
    from robot_sim.krc.packets import CommandPacket, ControlMode
    from robot_sim.world.teacher import DOWN

    cells = [RobotCell(valley(), seed=3, with_sensor=False) for _ in range(2)]
    if cells[0]._compiled is None:
        pytest.skip("no compiled cycle here (MuJoCo's, numpy's BLAS or the extension's C functions are missing)")
    start = np.array([0.6, -0.08, 0.26])
    for cell in cells:
        cell.place_tcp(start, DOWN)
        cell.start()
        cell.fri.request_command_mode()
    target = np.hstack([DOWN, (start - [0.0, 0.0, 0.06])[:, None]]).ravel()
    hand = np.array([0.0, 8.0, -20.0, 0.0, 0.0, 0.0])
    in_cmd = bridged = refused = 0
    for k in range(1500):
        stiffness = [2e9] * 3 + [150.0] * 3 if k > 700 and k % 97 == 0 else [2000.0] * 3 + [150.0] * 3
        outcomes = []
        for i, cell in enumerate(cells):
            cell.krc.gravity_compensation = k < 300
            m = cell.begin_cycle()
            if k < 1000 or k % 7:
                add = [float(k % 5), 0.0, -1.0, 0.3, -0.2, 0.1]  # FRI order: Tz, Ty, Tx
                if i == 0:
                    cell.receive(CommandPacket(m.seq, target.copy(), np.array(stiffness), np.full(6, 0.7), np.array(add),
                                               requested_mode=ControlMode.CART_IMP), m.stamp_ns + 100_000)
                else:
                    cell.fri.receive_fields(m.seq, 2, target.tolist(), stiffness, [0.7] * 6, add, m.stamp_ns + 100_000)
            out = cell.end_cycle(hand if k < 300 else None).outcome if i == 0 else cell.close(hand if k < 300 else None)
            outcomes.append((out.seq, out.answered, out.bridged, out.hold, out.state, out.quality,
                             out.consecutive_misses, cell.fri.last_reject_reason))
        a, b = cells
        assert outcomes[0] == outcomes[1], k
        assert a.sim.data.qpos.tobytes() == b.sim.data.qpos.tobytes(), k
        assert a.sim.data.qvel.tobytes() == b.sim.data.qvel.tobytes(), k
        assert a.tool_wrench.tobytes() == b.tool_wrench.tobytes(), k
        assert a.contact_force.tobytes() == b.contact_force.tobytes() and a.touching == b.touching, k
        in_cmd += outcomes[0][4] == 2
        bridged += outcomes[0][2]
        refused += "outside" in outcomes[0][7]
        la, lb_ = a.fri.last_applied, b.fri.last_applied  # the packet made from the slot when asked for
        assert (la is None) == (lb_ is None), k
        if la is not None and k % 50 == 0:
            assert la.cart_pos.tobytes() == lb_.cart_pos.tobytes() and la.add_tcp_ft.tobytes() == lb_.add_tcp_ft.tobytes()
    assert in_cmd > 300 and bridged >= 3 and refused >= 5, (in_cmd, bridged, refused)
