"""Wire protocol of the cell-bridge network: sans-I/O (no sockets, no asyncio, no clocks)."""
