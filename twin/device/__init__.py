"""A device: the driver contract, and the actor that puts a driver on the bus."""
