"""The service: real-time sessions on a field link, the daemon (LoopManager), history, configuration and the demo."""
