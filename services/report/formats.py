"""The files a report can be written to (by suffix), apart from the drawing code so a bad name is refused at once."""

FORMATS = (".png", ".html", ".pdf")
