"""The asyncio service: links, time sync, the pipeline worker and the publisher."""
