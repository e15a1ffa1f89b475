"""pyserial URL handlers of the simulators (added to ``serial.protocol_handler_packages`` by
:func:`skinstretch.simulators.stress_links.register_url_handler`)."""
