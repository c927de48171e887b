"""Learning in the twin: stepped campaigns and workcells for gym environments, and policy files."""
