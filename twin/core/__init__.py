"""The kernel's base: lab time, messages and their keys, errors, plugins, random streams, the bus."""
