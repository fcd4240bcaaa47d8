"""The operator console: static HTML/CSS/JS (ES modules, no build step) served at ``/``."""
