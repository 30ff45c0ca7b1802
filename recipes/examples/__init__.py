"""Short programs that write the method out on small problems."""
