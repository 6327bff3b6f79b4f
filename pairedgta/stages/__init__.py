"""One module per stage of the graph generate -> pseudolabel -> evaluate -> plot."""
