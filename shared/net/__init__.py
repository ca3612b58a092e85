"""The bus: the wire format, Zenoh keys and sessions, security roles, the
delivery protocol and the control messages that start and stop runs."""
