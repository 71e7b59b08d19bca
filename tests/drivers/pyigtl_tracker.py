"""pyigtl as a tracker that fits the fixtures itself: for each capture of coded points, fits
each fixture's frame to them and sends it as a TRANSFORM message.

Usage: pyigtl_tracker.py SPEC_JSON. The spec: {"layout": {"C1": [[x, y, z], ...], "C2": ...}
(each fixture's points in its frame, mm, by index), "reject_above_mm": R, "captures":
[{"timestamp": T, "points": [[group, index, [x, y, z]], ...]}, ...]}. Serves OpenIGTLink on a
free loopback port, prints "port N", and once celld connects sends, per capture, the TRANSFORM
of C1 and of C2 (device names), both with the capture's timestamp: the least-squares rigid
fit (Kabsch), leaving out one by one the point furthest from the fit while it is further than
R and more than three remain.
"""

import json
import sys
import time

import numpy as np
import pyigtl


def kabsch(model, measured):
    """The 4x4 pose mapping model points onto measured ones, least squares."""
    p_mean, q_mean = model.mean(axis=0), measured.mean(axis=0)
    a = (measured - q_mean).T @ (model - p_mean)
    u, _, vt = np.linalg.svd(a)
    d = np.sign(np.linalg.det(u @ vt))
    rotation = u @ np.diag([1.0, 1.0, d]) @ vt
    pose = np.eye(4)
    pose[:3, :3] = rotation
    pose[:3, 3] = q_mean - rotation @ p_mean
    return pose


def fit(model, measured, reject_above_mm):
    keep = np.ones(len(model), dtype=bool)
    while True:
        pose = kabsch(model[keep], measured[keep])
        fitted = model @ pose[:3, :3].T + pose[:3, 3]
        residuals = np.where(keep, np.linalg.norm(measured - fitted, axis=1), -1.0)
        worst = int(np.argmax(residuals))
        if residuals[worst] <= reject_above_mm or keep.sum() <= 3:
            return pose
        keep[worst] = False


def main(path):
    with open(path, encoding="utf-8") as file:
        spec = json.load(file)
    layout = {name: np.array(points) for name, points in spec["layout"].items()}
    server = pyigtl.OpenIGTLinkServer(port=0)
    print(f"port {server.server_address[1]}", flush=True)
    deadline = time.time() + 20
    while not server.is_connected():
        if time.time() > deadline:
            raise SystemExit("celld never connected")
        time.sleep(0.01)
    for capture in spec["captures"]:
        for name in ("C1", "C2"):
            points = [p for p in capture["points"] if p[0] == name]
            model = np.array([layout[name][int(p[1])] for p in points])
            measured = np.array([p[2] for p in points])
            pose = fit(model, measured, spec["reject_above_mm"])
            message = pyigtl.TransformMessage(
                matrix=pose, timestamp=capture["timestamp"], device_name=name
            )
            server.send_message(message, wait=True)
    # Every message is on the wire once the queue is empty; closing keeps them in order.
    server.stop()


if __name__ == "__main__":
    main(sys.argv[1])
