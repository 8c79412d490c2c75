"""The experiment driver: how a scenario is run (``options``), the runner that walks its
stages (``runner``) through the episode protocol (``episode``) and the learn stage
(``learn``), each role's config (``configs``), one demonstration (``demonstration``),
sweeps, the realtime profile and progress bars."""
