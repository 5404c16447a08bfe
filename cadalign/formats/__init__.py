"""Code that knows file formats (lowest layer beside types/errors/io/config/geometry; never imports a stage)."""
