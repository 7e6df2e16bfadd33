"""Deployment: a trained policy as a standalone artifact (export), behind a network server
(server), and the client a robot script uses (client: numpy + msgpack + websockets only)."""
