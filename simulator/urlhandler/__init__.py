"""pySerial URL handlers for the simulated devices: `dxlsim://NAME` (protocol_dxlsim) and
`lightsim://NAME` (protocol_lightsim). pySerial finds them by this package's name once
:func:`simulator.serial_urls.install` has listed it."""
