"""What users read: pictures, photometry in lux, the report and progress."""
