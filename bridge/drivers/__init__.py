"""Motor drivers of the bridge, one module per device. Each module imports its device library
only when its driver is configured, so ``import bridge.drivers.beaglebone`` works anywhere."""
