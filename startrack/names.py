"""Proper names of bright stars, for labels on pictures (HIP number -> IAU name).

The names are those approved by the IAU Working Group on Star Names (WGSN,
IAU Catalog of Star Names), for the stars most often seen in star-tracker
fields: the brightest stars of every constellation and a few well-known
groups (the Pleiades, the Hyades).  Nicknames the WGSN did not adopt
("Navi", "Regor") are not used.
"""

PROPER_NAMES = {
    # The brightest stars (to about magnitude 2.5).
    32349: "Sirius", 30438: "Canopus", 69673: "Arcturus", 71683: "Rigil Kentaurus", 91262: "Vega",
    24608: "Capella", 24436: "Rigel", 37279: "Procyon", 7588: "Achernar", 27989: "Betelgeuse",
    68702: "Hadar", 97649: "Altair", 60718: "Acrux", 21421: "Aldebaran", 65474: "Spica", 80763: "Antares",
    37826: "Pollux", 113368: "Fomalhaut", 102098: "Deneb", 62434: "Mimosa", 49669: "Regulus", 33579: "Adhara",
    36850: "Castor", 61084: "Gacrux", 85927: "Shaula", 25336: "Bellatrix", 25428: "Elnath", 45238: "Miaplacidus",
    26311: "Alnilam", 26727: "Alnitak", 109268: "Alnair", 62956: "Alioth", 15863: "Mirfak", 54061: "Dubhe",
    34444: "Wezen", 90185: "Kaus Australis", 41037: "Avior", 67301: "Alkaid", 86228: "Sargas", 31681: "Alhena",
    100751: "Peacock", 30324: "Mirzam", 11767: "Polaris", 46390: "Alphard", 9884: "Hamal", 3419: "Diphda",
    677: "Alpheratz", 5447: "Mirach", 14576: "Algol", 746: "Caph", 8903: "Sheratan", 9640: "Almach",
    65378: "Mizar", 65477: "Alcor", 53910: "Merak", 58001: "Phecda", 59774: "Megrez", 72105: "Izar",
    76267: "Alphecca", 77070: "Unukalhai", 84345: "Rasalgethi", 86032: "Rasalhague", 87833: "Eltanin",
    92855: "Nunki", 105199: "Alderamin", 107315: "Enif", 113881: "Scheat", 113963: "Markab", 1067: "Algenib",
    112122: "Tiaki", 3179: "Schedar", 6686: "Ruchbah", 8886: "Segin", 2081: "Ankaa", 27366: "Saiph",
    26241: "Hatysa", 25930: "Mintaka", 26207: "Meissa", 22449: "Tabit", 28360: "Menkalinan", 23015: "Hassaleh",
    35904: "Aludra", 30122: "Furud", 36188: "Gomeisa", 42913: "Alsephina", 44816: "Suhail", 45941: "Markeb",
    39429: "Naos", 45556: "Aspidiske", 50583: "Algieba", 54872: "Zosma", 57632: "Denebola", 54879: "Chertan",
    50335: "Adhafera", 48455: "Rasalas", 47508: "Subra", 68933: "Menkent", 82273: "Atria", 100453: "Sadr",
    102488: "Aljanah", 95947: "Albireo", 98036: "Alshain", 97278: "Tarazed", 93194: "Sulafat", 92420: "Sheliak",
    72607: "Kochab", 75097: "Pherkad", 68756: "Thuban", 85670: "Rastaban", 14135: "Menkar", 10826: "Mira",
    8645: "Baten Kaitos", 13847: "Acamar", 18543: "Zaurak", 23875: "Cursa", 21393: "Theemin",
    25985: "Arneb", 25606: "Nihal", 26634: "Phact", 27628: "Wazn",
    # Sagittarius, Scorpius, Ophiuchus, Libra, Virgo, Corvus.
    93506: "Ascella", 89931: "Kaus Media", 88635: "Alnasl", 90496: "Kaus Borealis", 95347: "Rukbat",
    98066: "Terebellum", 94141: "Albaldah", 89341: "Polis", 78401: "Dschubba", 78820: "Acrab", 80112: "Alniyat",
    85696: "Lesath", 78265: "Fang", 79374: "Jabbah", 78104: "Iklil", 84012: "Sabik", 74785: "Zubeneschamali",
    72622: "Zubenelgenubi", 61941: "Porrima", 63608: "Vindemiatrix", 59803: "Gienah", 60965: "Algorab",
    61359: "Kraz", 53740: "Alkes",
    # Boötes, Canes Venatici, Ursa Major.
    67927: "Muphrid", 71075: "Seginus", 73555: "Nekkar", 63125: "Cor Caroli", 50372: "Tania Borealis",
    50801: "Tania Australis", 44127: "Talitha", 41704: "Muscida", 55219: "Alula Borealis",
    # The Pleiades and the Hyades.
    17702: "Alcyone", 17499: "Electra", 17573: "Maia", 17608: "Merope", 17531: "Taygeta", 17847: "Atlas",
    17851: "Pleione", 17489: "Celaeno", 17579: "Asterope", 20205: "Prima Hyadum", 20455: "Secunda Hyadum",
    20889: "Ain", 20894: "Chamukuy",
}


def star_label(hip: int) -> str:
    """``"HIP 24436 Rigel"`` for named stars, ``"HIP 12345"`` otherwise; a Gaia DR3 source id (the ``gaia``
    catalog's fainter stars, :func:`startrack.gaia.is_hipparcos_id`) is ``"Gaia DR3 4472832130942575872"``."""
    if int(hip) >= 200_000:
        return f"Gaia DR3 {int(hip)}"
    name = PROPER_NAMES.get(int(hip))
    return f"HIP {int(hip)} {name}" if name else f"HIP {int(hip)}"
