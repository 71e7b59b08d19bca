"""pyigtl receives the captures `celld twin-server`'s camera streams.

Usage: pyigtl_receiver.py IGTL_PORT COUNT. Prints one JSON line per POINT message received:
{"version", "device", "timestamp", "points": [[group, name, [x, y, z]], ...]}.
"""

import json
import sys
import time

import pyigtl


def main(port, count):
    client = pyigtl.OpenIGTLinkClient(host="127.0.0.1", port=port)
    received = 0
    deadline = time.time() + 20
    while received < count:
        message = client.wait_for_message("camera", timeout=max(0.0, deadline - time.time()))
        if message is None:
            raise SystemExit(f"only {received} of {count} POINT messages within 20 s")
        assert message.message_type == "POINT", message.message_type
        points = [
            [group, name, [float(v) for v in position]]
            for group, name, position in zip(message.groups, message.names, message.positions)
        ]
        print(
            json.dumps(
                {
                    "version": message.header_version,
                    "device": message.device_name,
                    "timestamp": message.timestamp,
                    "points": points,
                }
            ),
            flush=True,
        )
        received += 1
    client.stop()


if __name__ == "__main__":
    main(int(sys.argv[1]), int(sys.argv[2]))
