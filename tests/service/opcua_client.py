"""A plant's OPC UA client (asyncua, PyPI) against celld's OPC UA server.

Checks, printing one line each and `ok` at the end (exit status 1 at the first failure):
browse paths to the cell's nodes; StateCurrent against StateCurrentName; a viewer can neither
write a variable nor call Start (BadUserAccessDenied); a wrong password and an anonymous user
are refused; an operator's Start answers a job id, while subscriptions see StateCurrent reach
Execute, ProdProcessedCount rise and a job-end event arrive from Cell at a low severity;
Basic256Sha256 Sign & Encrypt is refused until the client's
certificate is moved from the server's rejected/ to trusted/, then works.

Everything about the server comes from arguments (or the environment variable in brackets), so
that the same script runs against a test's server or a real `celld serve`:
  --url (OPCUA_URL)                   opc.tcp://host:port/
  --operator-user/--operator-token    an operator's user name and celld API token
  --viewer-user/--viewer-token        a viewer's
  --pki (OPCUA_PKI)                   the server's PKI directory (own/cert.der, trusted/, rejected/)
  --controller                        the controller Start runs (default expert)
  --initial-state                     the PackML state expected before Start (default: any)
  --timeout                           seconds to wait for each expected change (default 30)
  --http (CELLD_URL)                  the service's HTTP API; given, also checks the abort cycle:
                                      an e-stop over HTTP shows as Aborted with EmergencyStop true
                                      and an alarm event; Reset is refused there; Clear, then
                                      Reset, bring the cell to Idle; Stop and Reset likewise
"""

import argparse
import asyncio
import os
import shutil
import socket
import sys
import tempfile
import urllib.request
from pathlib import Path

from asyncua import Client, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from cryptography.x509.oid import ExtendedKeyUsageOID

NAMESPACE = "urn:celld:cell"
# ISA-TR88 / OPC 30050 state numbers.
STATES = {
    "Clearing": 1, "Stopped": 2, "Starting": 3, "Idle": 4, "Suspended": 5, "Execute": 6,
    "Stopping": 7, "Aborting": 8, "Aborted": 9, "Holding": 10, "Held": 11, "Unholding": 12,
    "Suspending": 13, "Unsuspending": 14, "Resetting": 15, "Completing": 16, "Complete": 17,
}
CLIENT_URI = "urn:celld:test-client"


def arguments():
    env = os.environ.get
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--url", default=env("OPCUA_URL"))
    p.add_argument("--operator-user", default=env("OPCUA_OPERATOR_USER", "operator"))
    p.add_argument("--operator-token", default=env("OPCUA_OPERATOR_TOKEN"))
    p.add_argument("--viewer-user", default=env("OPCUA_VIEWER_USER", "viewer"))
    p.add_argument("--viewer-token", default=env("OPCUA_VIEWER_TOKEN"))
    p.add_argument("--pki", default=env("OPCUA_PKI"))
    p.add_argument("--controller", default=env("OPCUA_CONTROLLER", "expert"))
    p.add_argument("--initial-state", default=env("OPCUA_INITIAL_STATE"))
    p.add_argument("--timeout", type=float, default=float(env("OPCUA_TIMEOUT", "30")))
    p.add_argument("--http", default=env("CELLD_URL"))
    args = p.parse_args()
    for name in ("url", "operator_token", "viewer_token", "pki"):
        if not getattr(args, name):
            p.error(f"--{name.replace('_', '-')} is required")
    return args


class Failed(Exception):
    pass


def check(condition, what):
    if not condition:
        raise Failed(what)
    print(f"ok: {what}", flush=True)


def client(args, user, password):
    c = Client(args.url, timeout=args.timeout)
    c.application_uri = CLIENT_URI
    c.set_user(user)
    c.set_password(password)
    return c


async def nodes(c):
    ns = await c.get_namespace_index(NAMESPACE)
    objects = c.nodes.objects

    async def at(*path):
        return await objects.get_child([f"{ns}:{name}" for name in ("Cell",) + path])

    return ns, at


class Changes:
    """Data changes and events, as they arrive."""

    def __init__(self):
        self.values = {}
        self.events = []
        self.arrived = asyncio.Event()

    def datachange_notification(self, node, value, data):
        self.values.setdefault(node.nodeid, []).append(value)
        self.arrived.set()

    def event_notification(self, event):
        self.events.append(event)
        self.arrived.set()

    async def until(self, condition, what, timeout):
        deadline = asyncio.get_running_loop().time() + timeout
        while not condition():
            left = deadline - asyncio.get_running_loop().time()
            if left <= 0:
                raise Failed(f"timed out waiting for {what}")
            self.arrived.clear()
            try:
                await asyncio.wait_for(self.arrived.wait(), left)
            except asyncio.TimeoutError:
                pass
        check(True, what)


async def refused_with(coroutine, status_name):
    try:
        await coroutine
    except ua.UaStatusCodeError as e:
        return type(e).__name__ == status_name or status_name in str(e)
    return False


async def viewer_checks(args):
    async with client(args, args.viewer_user, args.viewer_token) as c:
        ns, at = await nodes(c)
        state = await (await at("PackML", "Status", "StateCurrent")).read_value()
        name = await (await at("PackML", "Status", "StateCurrentName")).read_value()
        check(STATES.get(name) == state, f"StateCurrent {state} is {name}")
        if args.initial_state:
            check(name == args.initial_state, f"the cell is {args.initial_state}")
        for path in (
            ("Identification", "Manufacturer"), ("Identification", "SerialNumber"),
            ("PackML", "Status", "UnitModeCurrent"), ("PackML", "Status", "StopReason", "ID"),
            ("PackML", "Admin", "ProdDefectiveCount"), ("PackML", "Admin", "MeanCycleTime"),
            ("Job", "Id"), ("Job", "PoseErrorMm"), ("Safety", "EmergencyStop"),
            ("Alarms", "ActiveAlarms"), ("Alarms", "ActiveAlarmCount"),
        ):
            await (await at(*path)).read_value()
        check(True, "every browse path reads")
        estop = await at("Safety", "EmergencyStop")
        written = False
        try:
            await estop.write_value(ua.DataValue(ua.Variant(False, ua.VariantType.Boolean)))
            written = True
        except ua.UaStatusCodeError:
            pass
        check(not written, "a viewer cannot write Safety.EmergencyStop")
        cell = await at()
        check(
            await refused_with(
                cell.call_method(f"{ns}:Start", ua.Variant(args.controller, ua.VariantType.String),
                                 ua.Variant(-1, ua.VariantType.Int64)),
                "BadUserAccessDenied"),
            "a viewer's Start is refused with BadUserAccessDenied")


async def refused_sign_in(c):
    try:
        async with c:
            return False
    except Exception:  # asyncua raises the server's status or its own errors
        return True


async def bad_sign_ins(args):
    check(await refused_sign_in(client(args, args.operator_user, args.operator_token + "-wrong")),
          "a wrong password is refused")
    check(await refused_sign_in(Client(args.url, timeout=args.timeout)),
          "anonymous sign-in is refused")


async def operator_checks(args):
    async with client(args, args.operator_user, args.operator_token) as c:
        ns, at = await nodes(c)
        state = await at("PackML", "Status", "StateCurrent")
        count = await at("PackML", "Admin", "ProdProcessedCount")
        cell = await at()
        before = await count.read_value()
        changes = Changes()
        subscription = await c.create_subscription(50, changes)
        await subscription.subscribe_data_change([state, count], queuesize=16,
                                                 sampling_interval=0)
        await subscription.subscribe_events(cell)
        job = await cell.call_method(f"{ns}:Start",
                                     ua.Variant(args.controller, ua.VariantType.String),
                                     ua.Variant(-1, ua.VariantType.Int64))
        check(isinstance(job, int) and job > 0, f"an operator's Start answers job {job}")
        await changes.until(lambda: STATES["Execute"] in changes.values.get(state.nodeid, []),
                            "the subscription sees StateCurrent Execute", args.timeout)
        await changes.until(lambda: any(v > before for v in changes.values.get(count.nodeid, [])),
                            f"the subscription sees ProdProcessedCount rise above {before}",
                            args.timeout)
        ended = lambda: [e for e in changes.events if f"job {job} ended" in (e.Message.Text or "")]
        await changes.until(ended, f"an event says job {job} ended", args.timeout)
        event = ended()[0]
        check(event.SourceName == "Cell" and 1 <= event.Severity <= 200,
              f"from Cell at a low severity ({event.SourceName}, {event.Severity})")
        await subscription.delete()


def http_estop(args):
    request = urllib.request.Request(
        f"{args.http.rstrip('/')}/api/cell/estop", method="POST",
        headers={"Authorization": f"Bearer {args.operator_token}"})
    with urllib.request.urlopen(request, timeout=args.timeout) as answer:
        return answer.status


async def abort_cycle(args):
    async with client(args, args.operator_user, args.operator_token) as c:
        ns, at = await nodes(c)
        state = await at("PackML", "Status", "StateCurrent")
        estop = await at("Safety", "EmergencyStop")
        reason = await at("PackML", "Status", "StopReason", "ID")
        cell = await at()
        changes = Changes()
        subscription = await c.create_subscription(50, changes)
        await subscription.subscribe_data_change([state, estop], queuesize=16,
                                                 sampling_interval=0)
        await subscription.subscribe_events(cell)
        latest = lambda node: (changes.values.get(node.nodeid) or [None])[-1]
        status = await asyncio.get_running_loop().run_in_executor(None, http_estop, args)
        check(status == 200, "an e-stop over HTTP answers 200")
        await changes.until(lambda: latest(state) == STATES["Aborted"] and latest(estop) is True,
                            "the subscription sees Aborted and EmergencyStop true", args.timeout)
        check(await reason.read_value() == 1, "StopReason.ID is 1 (e-stop)")
        alarms = lambda: [e for e in changes.events if e.Severity >= 900]
        await changes.until(alarms, "an alarm event for the e-stop", args.timeout)
        method = lambda name: cell.call_method(f"{ns}:{name}")
        check(await refused_with(method("Reset"), "BadInvalidState"),
              "Reset in Aborted is refused with BadInvalidState")
        await method("Clear")
        await changes.until(lambda: latest(state) == STATES["Stopped"] and latest(estop) is False,
                            "Clear: Stopped and EmergencyStop false", args.timeout)
        await method("Reset")
        await changes.until(lambda: latest(state) == STATES["Idle"], "Reset: Idle", args.timeout)
        await method("Stop")
        await changes.until(lambda: latest(state) == STATES["Stopped"], "Stop: Stopped",
                            args.timeout)
        check(await reason.read_value() == 3, "StopReason.ID is 3 (stop)")
        check(await refused_with(
            cell.call_method(f"{ns}:Start", ua.Variant(args.controller, ua.VariantType.String),
                             ua.Variant(-1, ua.VariantType.Int64)), "BadInvalidState"),
            "Start in Stopped is refused with BadInvalidState")
        await method("Reset")
        await changes.until(lambda: latest(state) == STATES["Idle"], "Reset: Idle again",
                            args.timeout)
        await subscription.delete()


async def encrypted(args, work):
    key, cert = work / "client-key.pem", work / "client-cert.der"
    await setup_self_signed_certificate(
        key, cert, CLIENT_URI, socket.gethostname(), [ExtendedKeyUsageOID.CLIENT_AUTH],
        {"commonName": "celld test client", "organizationName": "celld"})
    pki = Path(args.pki)

    async def connect():
        c = client(args, args.viewer_user, args.viewer_token)
        await c.set_security(SecurityPolicyBasic256Sha256, certificate=str(cert),
                             private_key=str(key), server_certificate=str(pki / "own/cert.der"),
                             mode=ua.MessageSecurityMode.SignAndEncrypt)
        async with c:
            _, at = await nodes(c)
            return await (await at("PackML", "Status", "StateCurrent")).read_value()

    seen = set((pki / "rejected").glob("*.der"))
    untrusted = False
    try:
        await connect()
    except Exception:
        untrusted = True
    check(untrusted, "an unknown client certificate is refused")
    rejected = sorted(set((pki / "rejected").glob("*.der")) - seen)
    check(len(rejected) == 1, f"it waits in rejected/: {[p.name for p in rejected]}")
    # What an administrator does to trust it.
    shutil.move(str(rejected[0]), str(pki / "trusted" / rejected[0].name))
    state = await connect()
    check(state in STATES.values(), f"Sign & Encrypt (Basic256Sha256) reads StateCurrent {state}")


async def main():
    args = arguments()
    await viewer_checks(args)
    await bad_sign_ins(args)
    await operator_checks(args)
    if args.http:
        await abort_cycle(args)
    with tempfile.TemporaryDirectory() as work:
        await encrypted(args, Path(work))
    print("ok")


if __name__ == "__main__":
    try:
        asyncio.run(main())
    except Failed as e:
        print(f"FAILED: {e}", flush=True)
        sys.exit(1)
