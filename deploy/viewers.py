# Dashboard viewers for the viewer benchmarks (tests/tests/viewers.rs and
# deploy/bench-viewers.sh): opens N event streams on host:port, prints "ready" once
# each has its first `sessions` event, then keeps reading them all; exits with a
# message when any is refused or closed. Python's asyncio, standard library only.
import asyncio
import sys

host, port, n = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
ready = 0


async def viewer():
    global ready
    r, w = await asyncio.open_connection(host, port)
    w.write(f"GET /api/v1/events HTTP/1.1\r\nHost: {host}\r\nAccept: text/event-stream\r\n\r\n".encode())
    await w.drain()
    seen = b""
    while b"event: sessions" not in seen:
        chunk = await r.read(65536)
        if not chunk:
            sys.exit(f"a viewer's stream closed: {seen[:200]!r}")
        seen += chunk
        if len(seen) >= 12 and not seen.startswith(b"HTTP/1.1 200"):
            sys.exit(f"a viewer was refused: {seen[:200]!r}")
    ready += 1
    if ready == n:
        print("ready", flush=True)
    while await r.read(65536):
        pass
    sys.exit("a viewer's stream closed")


async def main():
    await asyncio.gather(*(viewer() for _ in range(n)))


asyncio.run(main())
