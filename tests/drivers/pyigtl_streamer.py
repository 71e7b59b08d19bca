"""pyigtl as a streaming camera: sends POINT captures at a fixed rate, whoever listens.

Usage: pyigtl_streamer.py CAPTURES_JSON HZ. Serves OpenIGTLink on a free loopback port,
prints "port N", and once a client connects sends the captures of the JSON file (a list of
[[group, name, [x, y, z]], ...]) round and round, one every 1/HZ s, each stamped with the time
it is sent, until the client leaves (or two minutes pass).
"""

import json
import sys
import time

import pyigtl


def main(path, hz):
    with open(path, encoding="utf-8") as file:
        captures = json.load(file)
    server = pyigtl.OpenIGTLinkServer(port=0)
    print(f"port {server.server_address[1]}", flush=True)
    deadline = time.time() + 20
    while not server.is_connected():
        if time.time() > deadline:
            raise SystemExit("celld never connected")
        time.sleep(0.01)
    period = 1.0 / hz
    end = time.time() + 120
    k = 0
    while server.is_connected() and time.time() < end:
        points = captures[k % len(captures)]
        message = pyigtl.PointMessage(
            positions=[p[2] for p in points],
            names=[p[1] for p in points],
            groups=[p[0] for p in points],
            timestamp=time.time(),
            device_name="camera",
        )
        server.send_message(message, wait=False)
        k += 1
        time.sleep(period)
    server.stop()


if __name__ == "__main__":
    main(sys.argv[1], float(sys.argv[2]))
