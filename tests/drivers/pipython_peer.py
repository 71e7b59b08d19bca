"""PI's own GCS library (PIPython) drives `celld twin-server` as it would a PI hexapod controller.

Usage: pipython_peer.py GCS_PORT. The server must start unreferenced (--unreferenced).
Prints "ok" and exits 0 when every answer is what PIPython expects; raises otherwise.
"""

import sys

from pipython import GCSDevice, GCSError, gcserror
from pipython.pidevice.interfaces.pisocket import PISocket

AXES = ["X", "Y", "Z", "U", "V", "W"]


def expect_error(code, action):
    try:
        action()
    except GCSError as error:
        assert error.val == code, f"expected GCS error {code}, got {error.val}: {error}"
        return
    raise AssertionError(f"expected GCS error {code}, got none")


def main(port):
    gateway = PISocket(host="127.0.0.1", port=port)
    with GCSDevice(gateway=gateway) as pidevice:
        # Connect and identify: PIPython picks its GCS 2 command set from CSV?.
        assert "twin hexapod" in pidevice.qIDN(), pidevice.qIDN()
        assert pidevice.qCSV() == 2.0
        assert type(pidevice.gcsdevice).__name__ == "GCS2Device", type(pidevice.gcsdevice)
        assert pidevice.qSAI() == AXES, pidevice.qSAI()
        assert pidevice.IsControllerReady() is True

        # After power-on: servos off, not referenced, and a move is refused with error 5.
        assert pidevice.qSVO() == {axis: False for axis in AXES}, pidevice.qSVO()
        assert pidevice.qFRF() == {axis: False for axis in AXES}, pidevice.qFRF()
        expect_error(gcserror.E5_PI_CNTR_MOVE_WITHOUT_REF_OR_NO_SERVO, lambda: pidevice.MOV("Z", 1.0))

        # Servo on, reference.
        pidevice.SVO(AXES, [True] * 6)
        assert pidevice.qSVO() == {axis: True for axis in AXES}
        pidevice.FRF()
        assert pidevice.qFRF() == {axis: True for axis in AXES}
        assert pidevice.qFRF("Z") == {"Z": True}

        # Velocity.
        pidevice.VLS(5.0)
        assert pidevice.qVLS() == 5.0
        expect_error(gcserror.E8_PI_CNTR_VEL_OUT_OF_LIMITS, lambda: pidevice.VLS(1000.0))

        # Move, wait for on-target, read the position back.
        start = pidevice.qPOS()
        assert list(start) == AXES, start
        target = {"X": start["X"] + 0.5, "Z": start["Z"] - 1.25}
        pidevice.MOV(list(target), list(target.values()))
        while not all(pidevice.qONT().values()):
            pass
        assert pidevice.IsMoving() == {axis: False for axis in AXES}
        position = pidevice.qPOS()
        for axis, value in target.items():
            assert abs(position[axis] - value) < 1e-9, (axis, position[axis], value)
        assert abs(pidevice.qMOV("X")["X"] - target["X"]) < 1e-9
        pidevice.MVR("Y", 0.25)
        assert abs(pidevice.qPOS("Y")["Y"] - (start["Y"] + 0.25)) < 1e-9

        # A pose outside the workspace: error 7, and the platform stays.
        expect_error(gcserror.E7_PI_CNTR_POS_OUT_OF_LIMITS, lambda: pidevice.MOV("Z", 1e5))
        assert abs(pidevice.qPOS("Z")["Z"] - target["Z"]) < 1e-9

        # Unknown axis and unknown command.
        expect_error(gcserror.E15_PI_CNTR_INVALID_AXIS_IDENTIFIER, lambda: pidevice.MOV("Q", 1.0))
        expect_error(gcserror.E2_PI_CNTR_UNKNOWN_COMMAND, lambda: pidevice.gcscommands._msgs.send("XYZ 1"))

        # Pivot point: readable; settable only while U V W are all 0.
        assert set(pidevice.qSPI()) == {"R", "S", "T"}, pidevice.qSPI()

        # Stop: STP, HLT and #24 leave error 10, which PIPython masks on request.
        pidevice.STP(noraise=True)
        pidevice.HLT(noraise=True)
        pidevice.StopAll(noraise=True)
        expect_error(gcserror.E10_PI_CNTR_STOP, lambda: pidevice.STP())
        # Errors are read and cleared.
        assert pidevice.qERR() == 0
    print("ok")


if __name__ == "__main__":
    main(int(sys.argv[1]))
