"""Gap certification: basis, scenario program, bounds, Lipschitz/variance estimates, certificate, audit."""
