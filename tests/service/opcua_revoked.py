"""An operator's OPC UA session whose token is revoked while it is open calls nothing more.

Arguments: --url, --http (the service's HTTP API), --admin-token, --operator-token, --token-id.
Prints one line per check and `ok` at the end; exit status 1 at the first failure.
"""

import argparse
import asyncio
import sys
import urllib.request

from asyncua import Client, ua


async def main():
    p = argparse.ArgumentParser(description=__doc__)
    for name in ("--url", "--http", "--admin-token", "--operator-token", "--token-id"):
        p.add_argument(name, required=True)
    args = p.parse_args()
    c = Client(args.url, timeout=30)
    c.set_user("operator")
    c.set_password(args.operator_token)
    async with c:
        ns = await c.get_namespace_index("urn:celld:cell")
        cell = await c.nodes.objects.get_child([f"{ns}:Cell"])
        await cell.call_method(f"{ns}:Stop")
        print("ok: the operator's Stop is taken", flush=True)
        request = urllib.request.Request(
            f"{args.http.rstrip('/')}/api/tokens/{args.token_id}", method="DELETE",
            headers={"Authorization": f"Bearer {args.admin_token}"})
        with urllib.request.urlopen(request, timeout=30) as answer:
            assert answer.status == 200, answer.status
        print("ok: the token is revoked over HTTP", flush=True)
        try:
            await cell.call_method(f"{ns}:Reset")
        except ua.UaStatusCodeError as e:
            if "BadUserAccessDenied" not in type(e).__name__ + str(e):
                print(f"failed: Reset was refused with {e!r}, not BadUserAccessDenied")
                sys.exit(1)
            print("ok: the same session's Reset is refused with BadUserAccessDenied", flush=True)
        else:
            print("failed: the revoked token's session still reset the cell")
            sys.exit(1)
    print("ok")


if __name__ == "__main__":
    asyncio.run(main())
