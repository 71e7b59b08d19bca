#!/usr/bin/env python3
"""A client of `celld serve` driven by its OpenAPI description (Python standard library only).

It fetches /api/openapi.json and calls the operations it describes by operationId
(`jobs_list`, `jobs_create`, `policies_read`...),
sending each parameter where the description puts it (path or query) and the body as the
operation takes it (JSON, or raw bytes for an upload). A refusal raises ApiError with the
status and the service's own `code` and `message`.

    python3 examples/python/celld_client.py [--url URL] [--token TOKEN] [--controller NAME]
        [--seed N] [--operations]

The URL defaults to CELLD_URL, else http://127.0.0.1:8080; the token to CELLD_TOKEN, else the
first line of --token-file (default data/admin.token, which `celld serve` writes on its first
start). Run as a program it lists the latest jobs, starts a job (operator or admin) and reads
it back until it ends; the last line is `job ID ended STATUS ...`. --operations lists every
operation the description has instead. Exits non-zero when the service refuses.
"""

import argparse
import json
import os
import sys
import time
import urllib.error
import urllib.parse
import urllib.request


class ApiError(Exception):
    """A refusal or failure: the HTTP status and the service's error body."""

    def __init__(self, operation, status, code, message):
        super().__init__(f"{operation}: {status} {code}: {message}")
        self.status = status
        self.code = code
        self.message = message


class Operation:
    """One operation of the description: its method, path template and parameters."""

    def __init__(self, method, path, spec):
        self.method = method.upper()
        self.path = path
        self.spec = spec
        self.parameters = {p["name"]: p for p in spec.get("parameters", [])}
        self.body_types = list(spec.get("requestBody", {}).get("content", {}))

    def summary(self):
        return (self.spec.get("description") or self.spec.get("summary") or "").split("\n")[0]


class Celld:
    """The service at `url`, called with `token`, as its OpenAPI description says."""

    def __init__(self, url, token, timeout_s=30.0):
        self.url = url.rstrip("/")
        self.token = token
        self.timeout_s = timeout_s
        self.description = self._send("GET", "/api/openapi.json", "openapi", None, None)
        self.operations = {}
        for path, item in self.description["paths"].items():
            for method, spec in item.items():
                name = spec["operationId"]
                if name in self.operations:
                    raise ValueError(f"the description names {name} twice")
                self.operations[name] = Operation(method, path, spec)

    def call(self, name, body=None, **parameters):
        """Calls operation `name` (its operationId) with its path and query parameters and
        an optional body (JSON-able, or bytes for an upload); answers the decoded JSON, or the
        text of a non-JSON answer."""
        operation = self.operations.get(name)
        if operation is None:
            raise ValueError(f"no operation {name}; the description has {sorted(self.operations)}")
        unknown = set(parameters) - set(operation.parameters)
        if unknown:
            raise ValueError(
                f"{name} takes no parameter {sorted(unknown)}; it takes {sorted(operation.parameters)}"
            )
        path = operation.path
        query = {}
        for pname, spec in operation.parameters.items():
            if pname not in parameters:
                if spec.get("required"):
                    raise ValueError(f"{name} needs the {spec['in']} parameter {pname}")
                continue
            value = parameters[pname]
            if spec["in"] == "path":
                path = path.replace("{" + pname + "}", urllib.parse.quote(str(value), safe=""))
            else:
                query[pname] = "true" if value is True else "false" if value is False else value
        if query:
            path += "?" + urllib.parse.urlencode(query)
        if body is not None and not operation.body_types:
            raise ValueError(f"{name} takes no body")
        content_type = None
        if body is not None:
            if isinstance(body, (bytes, bytearray)):
                content_type = next(
                    (t for t in operation.body_types if t != "application/json"),
                    "application/octet-stream",
                )
            else:
                content_type = "application/json"
                body = json.dumps(body).encode()
        return self._send(operation.method, path, name, body, content_type)

    def _send(self, method, path, name, body, content_type):
        request = urllib.request.Request(self.url + path, data=body, method=method)
        request.add_header("Authorization", f"Bearer {self.token}")
        if content_type:
            request.add_header("Content-Type", content_type)
        try:
            with urllib.request.urlopen(request, timeout=self.timeout_s) as answer:
                text = answer.read().decode()
                if answer.headers.get_content_type() == "application/json":
                    return json.loads(text)
                return text
        except urllib.error.HTTPError as error:
            text = error.read().decode(errors="replace")
            try:
                detail = json.loads(text)["error"]
                code, message = detail["code"], detail["message"]
            except (ValueError, KeyError, TypeError):
                code, message = "?", text
            raise ApiError(f"{method} {path}", error.code, code, message) from None
        except urllib.error.URLError as error:
            raise ConnectionError(
                f"{method} {path}: cannot reach celld at {self.url} ({error.reason}); "
                "is `celld serve` running there?"
            ) from None


def token_from(args):
    if args.token:
        return args.token
    if os.environ.get("CELLD_TOKEN"):
        return os.environ["CELLD_TOKEN"]
    try:
        with open(args.token_file) as file:
            return file.readline().strip()
    except OSError as error:
        sys.exit(f"celld_client: no token: give --token or CELLD_TOKEN, or a readable "
                 f"--token-file ({args.token_file}: {error.strerror})")


def job_line(job):
    reason = f" ({job['failure_reason']})" if job.get("failure_reason") else ""
    reward = "-" if job.get("reward") is None else f"{job['reward']:.3f}"
    return (f"job {job['id']}  {job['status']}{reason}  {job['controller']}  seed {job['seed']}  "
            f"{job['steps']} steps  reward {reward}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--url", default=os.environ.get("CELLD_URL", "http://127.0.0.1:8080"))
    parser.add_argument("--token", help="the bearer token (default: CELLD_TOKEN, else --token-file)")
    parser.add_argument("--token-file", default="data/admin.token")
    parser.add_argument("--controller", default="expert", help="the job's controller")
    parser.add_argument("--seed", type=int, help="the job's seed (default: the service draws one)")
    parser.add_argument("--operations", action="store_true", help="list the operations and stop")
    args = parser.parse_args()

    try:
        celld = Celld(args.url, token_from(args))
        if args.operations:
            for name, operation in sorted(celld.operations.items()):
                print(f"{name:28} {operation.method:6} {operation.path}  {operation.summary()}")
            return 0

        me = celld.call("service_me")
        print(f"signed in as `{me['name']}` ({me['role']}); "
              f"{len(celld.operations)} operations described")
        page = celld.call("jobs_list", limit=5)
        print(f"{len(page['items'])} of {page['total']} jobs")
        for job in page["items"]:
            print("  " + job_line(job))

        request = {"controller": args.controller}
        if args.seed is not None:
            request["seed"] = args.seed
        job = celld.call("jobs_create", request)
        print(f"job {job['id']} {job['status']}: controller {job['controller']}, seed {job['seed']}")
        status = job["status"]
        while job["status"] in ("queued", "running"):
            time.sleep(0.2)
            job = celld.call("jobs_read", id=job["id"])
            if job["status"] != status:
                status = job["status"]
                print(f"job {job['id']} {status}")
        steps = celld.call("jobs_read_steps", id=job["id"])["items"]
        reason = f" ({job['failure_reason']})" if job.get("failure_reason") else ""
        reward = "-" if job.get("reward") is None else f"{job['reward']:.3f}"
        print(f"job {job['id']} ended {job['status']}{reason}: {job['steps']} steps "
              f"({len(steps)} stored), reward {reward}")
        return 0
    except (ApiError, ConnectionError, ValueError) as error:
        print(f"celld_client: {error}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
