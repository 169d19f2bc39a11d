"""gonio.fitting: objectives, the nlopt driver, uncertainty, model selection, exports."""
