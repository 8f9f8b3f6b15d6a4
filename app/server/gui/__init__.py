"""The presenter's page in viser: the scene, the controls, the plots and the lab tabs."""
