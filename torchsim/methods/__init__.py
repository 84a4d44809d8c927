"""Solution methods for joints, limits and contacts: ``spring`` (penalty forces and velocity impulses, in the
spirit of Brax v1) and ``xpbd`` (position-based projection, after Mueller et al. 2020, "Detailed Rigid Body
Simulation with Extended Position Based Dynamics")."""
