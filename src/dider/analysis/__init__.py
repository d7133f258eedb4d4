"""Reading runs after the fact: sweep reports, committed records, the explorer, diagnoses,
search."""
