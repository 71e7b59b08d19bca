"""pyigtl sends POINT and TRANSFORM messages to celld's camera driver.

Usage: pyigtl_sender.py MESSAGES_JSON. Serves OpenIGTLink on a free loopback port, prints
"port N", and once celld connects sends the messages of the JSON file in order (a list of
{"type": "POINT", "version", "device", "timestamp", "points": [[group, name, [x, y, z]], ...]}
or {"type": "TRANSFORM", "version", "device", "timestamp", "matrix": 4x4}), then waits for
the queue to empty.
"""

import json
import sys
import time

import pyigtl


def message(spec):
    if spec["type"] == "POINT":
        points = spec["points"]
        built = pyigtl.PointMessage(
            positions=[p[2] for p in points],
            names=[p[1] for p in points],
            groups=[p[0] for p in points],
            timestamp=spec["timestamp"],
            device_name=spec["device"],
        )
    else:
        built = pyigtl.TransformMessage(
            matrix=spec["matrix"], timestamp=spec["timestamp"], device_name=spec["device"]
        )
    built.header_version = spec["version"]
    built.message_id = spec.get("message_id", 0)
    return built


def main(path):
    with open(path, encoding="utf-8") as file:
        specs = json.load(file)
    server = pyigtl.OpenIGTLinkServer(port=0)
    print(f"port {server.server_address[1]}", flush=True)
    deadline = time.time() + 20
    while not server.is_connected():
        if time.time() > deadline:
            raise SystemExit("celld never connected")
        time.sleep(0.01)
    for spec in specs:
        server.send_message(message(spec), wait=True)
    # Every message is on the wire once the queue is empty; closing keeps them in order.
    server.stop()
    print("sent", len(specs), flush=True)


if __name__ == "__main__":
    main(sys.argv[1])
