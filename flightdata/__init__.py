"""Flight data: the flight folder and its layout, the MCAP recorder and the flight-log reader."""
