"""Reading uploaded files with a size limit."""

from __future__ import annotations

from fastapi import UploadFile

from api.problems import Problem


async def read_limited(upload: UploadFile, field: str, limit: int) -> bytes:
    content = await upload.read(limit + 1)
    if len(content) > limit:
        raise Problem(413, "payload-too-large", f"{field}: {upload.filename!r} is larger than {limit} bytes.")
    return content
