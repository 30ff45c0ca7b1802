"""Reading saved runs: their config, tables and agents, the report and the studies of one run or many."""
