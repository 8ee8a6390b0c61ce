"""What goes to the shop floor: the calibrated model, the residual ELM, command correction through
inverse kinematics, and saving / loading models."""
