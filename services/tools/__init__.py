"""Commands that are tools rather than services of the data flow: the operators' queries and
imports, ``up`` (the stack), the router, the dead-letter printer, the security profile
generator, the planners' report and the gateway check."""
