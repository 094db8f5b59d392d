"""Formation control on board: the decentralised formation MPC, slot assignment and failsafe decisions."""
