"""pyserial URL handlers of the simulator (``sim://``).

``service.sources.handlers`` adds this package to pyserial's handler
packages, so that ``serial.serial_for_url("sim://?scene=press")`` opens a
simulated board through the same code path as hardware, a pty or TCP.
"""
