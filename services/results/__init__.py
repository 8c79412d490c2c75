"""What a run leaves for people: the typed run record the runner hands over (``record``),
the report as data and text (``report``, ``text``), the thesis' figures (``figures``),
the one-page HTML report (``html``) and ETAR against STAR (``compare``)."""
