"""pyserial URL handlers of the simulators (added to ``serial.protocol_handler_packages`` by
:func:`simulators.stresssim.register_url_handler`)."""
