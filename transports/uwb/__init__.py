"""The ``uwb`` transport: chunk/ack/resend over a UWB module's serial port (see ``docs/uwb.md``)."""
