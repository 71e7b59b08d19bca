"""Plant clients subscribed to celld's OPC UA server (asyncua), for `cargo bench --bench service`.

Each of --clients sessions signs in with --token and subscribes, at a 20 ms publishing interval,
to the PackML state, the part counters, the running job's step, pose error and sigma, and the
e-stop, and to the cell's events. Prints `ready` once every client is subscribed, then one line
`state <StateCurrent> <arrival> <source timestamp>` (unix s) per client and state notification
as it arrives, until stdin closes.
"""

import argparse
import asyncio
import logging
import sys
import time
from datetime import timezone

from asyncua import Client

NAMESPACE = "urn:celld:cell"
WATCHED = (
    ("PackML", "Status", "StateCurrent"),
    ("PackML", "Admin", "ProdProcessedCount"),
    ("PackML", "Admin", "ProdDefectiveCount"),
    ("Job", "Step"),
    ("Job", "PoseErrorMm"),
    ("Job", "SigmaMm"),
    ("Safety", "EmergencyStop"),
)


class Printer:
    def __init__(self, state):
        self.state = state
        self.first = True

    def datachange_notification(self, node, value, data):
        if node.nodeid == self.state:
            if self.first:  # the value when the subscription began, not a change
                self.first = False
                return
            arrived = time.time()
            source = data.monitored_item.Value.SourceTimestamp
            if source.tzinfo is None:
                source = source.replace(tzinfo=timezone.utc)
            print(f"state {value} {arrived:.6f} {source.timestamp():.6f}", flush=True)

    def event_notification(self, event):
        pass


async def client(args, ready):
    c = Client(args.url, timeout=30)
    c.set_user("bench")
    c.set_password(args.token)
    await c.connect()
    ns = await c.get_namespace_index(NAMESPACE)
    cell = await c.nodes.objects.get_child([f"{ns}:Cell"])
    nodes = [await cell.get_child([f"{ns}:{name}" for name in path]) for path in WATCHED]
    subscription = await c.create_subscription(20, Printer(nodes[0].nodeid))
    await subscription.subscribe_data_change(nodes, queuesize=16, sampling_interval=0)
    await subscription.subscribe_events(cell)
    ready.release()
    return c


async def main():
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--url", required=True)
    p.add_argument("--token", required=True)
    p.add_argument("--clients", type=int, default=20)
    args = p.parse_args()
    # asyncua warns of the plain-text password on every session (this is the None endpoint on
    # loopback) and of the session timeout it was granted: not the bench's business.
    logging.basicConfig(level=logging.ERROR)
    ready = asyncio.Semaphore(0)
    clients = await asyncio.gather(*(client(args, ready) for _ in range(args.clients)))
    print("ready", flush=True)
    await asyncio.get_running_loop().run_in_executor(None, sys.stdin.read)
    for c in clients:
        await c.disconnect()


if __name__ == "__main__":
    asyncio.run(main())
