"""Acquisition: sessions, the cycle loop, the MCAP recorder, supervision and the daemon."""
