"""The cells as a shared medium: who hears a transmission, carrier sense, and the datagrams that carry it between processes."""
