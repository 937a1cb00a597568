"""A TCP server on an asyncio loop of its own, in a daemon thread (``LoopServer``): the shape of the small HTTP
servers that must never give a connection a thread (``--metrics``, the Foxglove front). A subclass writes
``_serve(reader, writer)``; ``close`` stops the loop, cancelling every connection's task, from any thread."""

from __future__ import annotations

import asyncio
import threading

#: the listen backlog of every loop server
BACKLOG = 128


class LoopServer:
    """Listens on ``host``:``port`` (0: a free one, ``self.port`` says which) with ``_serve`` for each connection,
    lines read up to ``limit`` bytes, from a daemon thread called ``name``."""

    def __init__(self, host: str, port: int, name: str, limit: int) -> None:
        self.loop = asyncio.new_event_loop()
        self.server = self.loop.run_until_complete(
            asyncio.start_server(self._serve, host, port, limit=limit, backlog=BACKLOG)
        )
        self.port = int(self.server.sockets[0].getsockname()[1])
        self.thread = threading.Thread(target=self.loop.run_forever, name=name, daemon=True)
        self.thread.start()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        raise NotImplementedError  # pragma: no cover - each server answers its own

    def close(self) -> None:
        """Stop serving and close every connection (from any thread)."""
        if not self.thread.is_alive():
            return

        async def stop() -> None:
            self.server.close()
            tasks = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            self.loop.stop()

        asyncio.run_coroutine_threadsafe(stop(), self.loop)
        self.thread.join(5)
        if not self.thread.is_alive():
            self.loop.close()
