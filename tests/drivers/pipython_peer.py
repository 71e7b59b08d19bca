"""PI's own GCS library (PIPython) drives `celld twin-server` as it would a PI hexapod controller.

Usage: pipython_peer.py GCS_PORT. The server must start unreferenced (--unreferenced), with
timed moves (no --instant-moves). PIPython's helpers (pitools.startup, moveandwait,
waitontarget) run unmodified, with PIPython's own answer timeout: a command the twin left
unanswered fails here as PIPython's timeout error.
Prints "ok" and exits 0 when every answer is what PIPython expects; raises otherwise.
"""

import sys

from pipython import GCSDevice, GCSError, gcserror, pitools
from pipython.pidevice.common.gcscommands_helpers import getsupportedfunctions
from pipython.pidevice.interfaces.pisocket import PISocket

AXES = ["X", "Y", "Z", "U", "V", "W"]

# The PIPython functions whose commands the twin answers: each HasXXX() must say so.
ANSWERED = [
    "qIDN", "qHLP", "qHPA", "qVER", "qSSN", "qCSV", "qSAI", "qERR", "qCST", "qTMN", "qTMX",
    "qCCL", "CCL", "qRON", "RON", "qSPA", "SPA", "qVMO", "KEN", "qKEN", "KSD", "GetStatus",
    "IsMoving", "IsControllerReady", "StopAll", "MOV", "qMOV", "MVR", "qPOS", "qONT", "SVO",
    "qSVO", "FRF", "qFRF", "STP", "HLT", "VLS", "qVLS", "SPI", "qSPI",
]
# Commands a PI hexapod may have that the twin does not: PIPython must not send them.
NOT_ANSWERED = ["INI", "ONL", "EAX", "qOSN", "qVEL", "RNP", "FPH", "qTRS", "WPA"]


def expect_error(code, action):
    try:
        action()
    except GCSError as error:
        assert error.val == code, f"expected GCS error {code}, got {error.val}: {error}"
        return
    raise AssertionError(f"expected GCS error {code}, got none")


def close(a, b, tolerance=1e-9):
    return abs(a - b) < tolerance


def power_on(pidevice):
    """Connect and identify: PIPython picks its GCS 2 command set from CSV? and learns the
    commands from HLP?."""
    assert "twin hexapod" in pidevice.qIDN(), pidevice.qIDN()
    assert pidevice.qCSV() == 2.0
    assert type(pidevice.gcsdevice).__name__ == "GCS2Device", type(pidevice.gcsdevice)
    assert pidevice.qSAI() == AXES, pidevice.qSAI()
    assert pidevice.qSAI_ALL() == AXES, pidevice.qSAI_ALL()
    assert pidevice.IsControllerReady() is True
    for name in ANSWERED:
        assert getattr(pidevice, f"Has{name}")(), f"Has{name}() is False"
    for name in NOT_ANSWERED:
        assert not getattr(pidevice, f"Has{name}")(), f"Has{name}() is True"
    assert set(getsupportedfunctions(pidevice.qHLP())) >= set(ANSWERED)

    # After power-on: servos off, not referenced, and a move is refused with error 5.
    assert pidevice.qSVO() == {axis: False for axis in AXES}, pidevice.qSVO()
    assert pidevice.qFRF() == {axis: False for axis in AXES}, pidevice.qFRF()
    expect_error(gcserror.E5_PI_CNTR_MOVE_WITHOUT_REF_OR_NO_SERVO, lambda: pidevice.MOV("Z", 1.0))


def helpers(pidevice):
    """PIPython's own helpers, unmodified: startup references (FRF) and switches the servos
    on; moveandwait and waitontarget wait while the moves take their time."""
    pitools.startup(pidevice, refmodes="FRF")
    assert pidevice.qSVO() == {axis: True for axis in AXES}, pidevice.qSVO()
    assert pidevice.qFRF() == {axis: True for axis in AXES}, pidevice.qFRF()
    assert pidevice.qRON() == {axis: True for axis in AXES}, pidevice.qRON()
    pitools.waitonreferencing(pidevice)

    # Velocity.
    pidevice.VLS(5.0)
    assert pidevice.qVLS() == 5.0
    expect_error(gcserror.E8_PI_CNTR_VEL_OUT_OF_LIMITS, lambda: pidevice.VLS(1000.0))

    start = pidevice.qPOS()
    assert list(start) == AXES, start
    pitools.moveandwait(pidevice, "Z", start["Z"] - 1.25)
    assert close(pidevice.qPOS("Z")["Z"], start["Z"] - 1.25), pidevice.qPOS("Z")
    assert pidevice.IsMoving() == {axis: False for axis in AXES}

    target = {"X": start["X"] + 0.5, "Z": start["Z"]}
    pidevice.MOV(list(target), list(target.values()))
    pitools.waitontarget(pidevice)
    position = pidevice.qPOS()
    for axis, value in target.items():
        assert close(position[axis], value), (axis, position[axis], value)
    assert close(pidevice.qMOV("X")["X"], target["X"])
    pidevice.MVR("Y", 0.25)
    pitools.waitontarget(pidevice, "Y")
    assert close(pidevice.qPOS("Y")["Y"], start["Y"] + 0.25), pidevice.qPOS("Y")

    # A pose outside the workspace: error 7, and the platform stays.
    assert not pidevice.qVMO("Z", 1e5)
    expect_error(gcserror.E7_PI_CNTR_POS_OUT_OF_LIMITS, lambda: pidevice.MOV("Z", 1e5))
    assert close(pidevice.qPOS("Z")["Z"], target["Z"])


def user_session(pidevice):
    """What a user's script asks a hexapod, a stop in the middle of a move included."""
    assert "MOV" in pidevice.qHLP()
    assert "twin" in pidevice.qVER()
    assert pidevice.qCST() == {axis: "TWIN-6SPS" for axis in AXES}, pidevice.qCST()
    assert pidevice.qSSN().strip()
    assert pidevice.qCCL() == 0
    assert pidevice.qKEN() == {"ZERO": "ZERO"}, pidevice.qKEN()
    pidevice.KEN("ZERO")
    expect_error(gcserror.E34_PI_CNTR_CMD_NOT_ALLOWED_FOR_STAGE,
                 lambda: pidevice.KSD("USER", "Z", 10.0))
    low, high, position = pidevice.qTMN(), pidevice.qTMX(), pidevice.qPOS()
    for axis in AXES:
        assert low[axis] < position[axis] < high[axis], (axis, low[axis], position[axis], high[axis])
        assert pidevice.qSPA(axis, 0x15)[axis][0x15] == high[axis]
        assert pidevice.qSPA(axis, 0x30)[axis][0x30] == low[axis]
    assert pidevice.qVMO(AXES, [position[axis] for axis in AXES])

    # #4 is one character: it must not spoil the next command.
    status = pidevice.GetStatus()
    assert status & 0x9000 == 0x9000, hex(status)  # on target, servos on
    assert pidevice.qPOS("X")["X"] == position["X"]

    # A 20 mm move at 1 mm/s, stopped while it runs: the platform stays where it stopped.
    pidevice.VLS(1.0)
    x = position["X"]
    pidevice.MOV("X", x + 20.0)
    assert pidevice.IsMoving()["X"], pidevice.IsMoving()
    assert not pidevice.qONT("X")["X"]
    assert pidevice.GetStatus() & 0x2000, "in motion"
    pidevice.STP(noraise=True)
    stopped = pidevice.qPOS("X")["X"]
    assert x < stopped < x + 20.0, (x, stopped)
    assert pidevice.qONT() == {axis: True for axis in AXES}
    assert close(pidevice.qMOV("X")["X"], stopped)
    pitools.waitontarget(pidevice)
    pidevice.VLS(30.0)

    # Unknown axis, unknown command and unknown query: the next command is still answered.
    expect_error(gcserror.E15_PI_CNTR_INVALID_AXIS_IDENTIFIER, lambda: pidevice.MOV("Q", 1.0))
    expect_error(gcserror.E2_PI_CNTR_UNKNOWN_COMMAND, lambda: pidevice.gcscommands._msgs.send("XYZ 1"))
    expect_error(gcserror.E2_PI_CNTR_UNKNOWN_COMMAND, lambda: pidevice.gcscommands._msgs.send("XYZ? 1"))
    assert close(pidevice.qPOS("X")["X"], stopped)

    # Pivot point: readable; settable only while U V W are all 0.
    assert set(pidevice.qSPI()) == {"R", "S", "T"}, pidevice.qSPI()

    # Stop: STP, HLT and #24 leave error 10, which PIPython masks on request.
    pidevice.STP(noraise=True)
    pidevice.HLT(noraise=True)
    pidevice.StopAll(noraise=True)
    expect_error(gcserror.E10_PI_CNTR_STOP, lambda: pidevice.STP())
    # Errors are read and cleared.
    assert pidevice.qERR() == 0


def main(port):
    gateway = PISocket(host="127.0.0.1", port=port)
    with GCSDevice(gateway=gateway) as pidevice:
        power_on(pidevice)
        helpers(pidevice)
        user_session(pidevice)
    print("ok")


if __name__ == "__main__":
    main(int(sys.argv[1]))
