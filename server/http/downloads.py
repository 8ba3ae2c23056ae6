"""Stored files sent as they are on disk: read and sent in bounded chunks, never whole.

A character file can be hundreds of megabytes and a viewer can read slowly: each request
holds one chunk at a time (and uvicorn's write buffer, which pauses the sender while the
client does not read), whatever the file's size and the client's speed. No route here.
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Mapping
from typing import BinaryIO

import anyio
from fastapi.responses import StreamingResponse

__all__ = ["CHUNK_BYTES", "stream_file"]

#: Bytes read from disk and handed to the server at a time.
CHUNK_BYTES = 64 * 1024


def stream_file(
    fh: BinaryIO, size: int, media_type: str, headers: Mapping[str, str] | None = None
) -> StreamingResponse:
    """A response sending ``size`` bytes of ``fh`` from where it stands, then closing it.

    ``Content-Length`` is ``size``: a file cut short under it (it cannot be: stores write
    atomically, and an open file keeps the version it opened) ends the connection early
    rather than send other bytes.
    """
    return StreamingResponse(
        _chunks(fh, size),
        media_type=media_type,
        headers={**(headers or {}), "Content-Length": str(size)},
    )


async def _chunks(fh: BinaryIO, size: int) -> AsyncIterator[bytes]:
    try:
        left = size
        while left > 0:
            chunk = await anyio.to_thread.run_sync(fh.read, min(CHUNK_BYTES, left))
            if not chunk:
                return
            left -= len(chunk)
            yield chunk
    finally:
        fh.close()
