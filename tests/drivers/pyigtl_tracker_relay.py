"""pyigtl as a live tracker in front of a streaming camera: takes each capture of coded points
the camera streams, fits each fixture's frame to them and serves the frames as TRANSFORM
messages.

Usage: pyigtl_tracker_relay.py SPEC_JSON CAMERA_PORT [CAMERA_HOST]. The spec is
pyigtl_tracker.py's (its "layout" and "reject_above_mm"; "captures", if there, are not used),
with optionally "labels": {"C1": [label, ...], "C2": ...}, the name the camera gives each
layout point, by index (without it a point's name is its index). Connects as an OpenIGTLink
client to the camera (a POINT message per capture: each point's group its fixture, its name
its label), serves OpenIGTLink on a free loopback
port, prints "port N", and once celld connects sends, per capture, the TRANSFORM of C1 and of
C2 (device names), both with the capture's timestamp, fitted as pyigtl_tracker.py fits them.
A capture with fewer than three points on a fixture is passed over. Runs until stdin closes
or the process is killed.
"""

import json
import sys
import threading
import time

import numpy as np
import pyigtl

from pyigtl_tracker import fit


def fitted(capture, layout, indexes, reject_above_mm):
    """The capture's (fixture, 4x4 pose) pairs, or None when a fixture has too few points."""
    poses = []
    for name in ("C1", "C2"):
        points = [
            (indexes[name][label], position)
            for label, group, position in zip(capture.names, capture.groups, capture.positions)
            if group == name and label in indexes[name]
        ]
        if len(points) < 3:
            return None
        model = np.array([layout[name][index] for index, _ in points])
        measured = np.array([position for _, position in points], dtype=float)
        poses.append((name, fit(model, measured, reject_above_mm)))
    return poses


def watch_stdin(stop):
    """Sets `stop` once stdin closes: the process that started the relay has gone."""
    for _ in sys.stdin:
        pass
    stop.set()


def main(path, camera_port, camera_host):
    with open(path, encoding="utf-8") as file:
        spec = json.load(file)
    layout = {name: np.array(points) for name, points in spec["layout"].items()}
    reject_above_mm = spec["reject_above_mm"]
    labels = spec.get("labels", {})
    indexes = {
        name: {
            str(label): index
            for index, label in enumerate(labels.get(name, range(len(points))))
        }
        for name, points in layout.items()
    }
    camera = pyigtl.OpenIGTLinkClient(host=camera_host, port=camera_port)
    server = pyigtl.OpenIGTLinkServer(port=0)
    print(f"port {server.server_address[1]}", flush=True)
    stop = threading.Event()
    threading.Thread(target=watch_stdin, args=(stop,), daemon=True).start()
    deadline = time.time() + 20
    while not server.is_connected():
        if time.time() > deadline or stop.is_set():
            raise SystemExit("celld never connected")
        time.sleep(0.01)
    while not stop.is_set():
        # The newest capture since the last one (pyigtl keeps one message per device).
        capture = camera.wait_for_message("camera", timeout=0.1)
        if capture is None or capture.message_type != "POINT":
            continue
        poses = fitted(capture, layout, indexes, reject_above_mm)
        if poses is None:
            continue
        for name, pose in poses:
            message = pyigtl.TransformMessage(
                matrix=pose, timestamp=capture.timestamp, device_name=name
            )
            server.send_message(message, wait=False)
    camera.stop()
    server.stop()


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]), sys.argv[3] if len(sys.argv) > 3 else "127.0.0.1")
